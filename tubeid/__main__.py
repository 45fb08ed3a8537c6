from tubeid.cli import main

raise SystemExit(main())
