from tubeid.cli import entry

entry()
