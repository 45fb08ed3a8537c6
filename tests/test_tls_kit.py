"""cluster/tls/make-certs.sh: what goes where. (The kit running a TLS cluster end to end is
tests/test_runner_distributed.py::test_tls_cluster_from_the_cluster_settings.)

The directory the cluster README mounts in every pod (OUTPUT_DIR) must never hold the CA's private
key: whoever has it can issue certificates the cluster accepts. Keys are compared by their public
halves with openssl, not by file name.
"""

import shutil
import stat
import subprocess
from pathlib import Path

import pytest
import yaml

pytestmark = pytest.mark.skipif(shutil.which("openssl") is None, reason="needs openssl")
SCRIPT = Path(__file__).resolve().parents[1] / "cluster" / "tls" / "make-certs.sh"


def _make(*args, check=True):
    return subprocess.run(["bash", str(SCRIPT), *map(str, args)], capture_output=True, text=True, check=check)


def _openssl(*args) -> str:
    return subprocess.run(["openssl", *args], capture_output=True, text=True, check=True).stdout


def _public_of_key(path: Path) -> str:
    return _openssl("pkey", "-in", str(path), "-pubout")


def _private_keys(folder: Path) -> list[Path]:
    return [p for p in folder.rglob("*") if p.is_file() and "PRIVATE KEY" in p.read_text(errors="replace")]


def test_the_ca_key_never_lands_in_the_mounted_directory(tmp_path):
    out, ca = tmp_path / "tls", tmp_path / "tls.ca"
    _make(out)
    ca_public = _openssl("x509", "-in", str(ca / "ca.pem"), "-noout", "-pubkey")
    keys = _private_keys(out)
    assert sorted(k.name for k in keys) == ["client-key.pem", "scheduler-key.pem", "worker-key.pem"]
    assert all(_public_of_key(k) != ca_public for k in keys)
    assert _public_of_key(ca / "ca-key.pem") == ca_public  # the CA key is in CA_DIR, outside OUTPUT_DIR
    assert (out / "ca.pem").read_bytes() == (ca / "ca.pem").read_bytes()
    for folder in (out, ca):
        assert stat.S_IMODE(folder.stat().st_mode) == 0o700
        assert all(stat.S_IMODE(p.stat().st_mode) == 0o600 for p in folder.iterdir())
    for role in ("scheduler", "worker", "client"):
        assert f"{role}.pem: OK" in _openssl("verify", "-CAfile", str(out / "ca.pem"), str(out / f"{role}.pem"))
    config = yaml.safe_load((out / "dask-tls.yaml").read_text())["distributed"]["comm"]["tls"]
    files = [config["ca-file"]] + [config[r][k] for r in ("scheduler", "worker", "client") for k in ("cert", "key")]
    assert all(Path(f).parent == out.resolve() and Path(f).is_file() for f in files)


def test_a_second_run_issues_new_certificates_from_the_same_ca(tmp_path):
    out, ca = tmp_path / "tls", tmp_path / "offline-ca"
    _make(out, "DNS:localhost", ca)
    first_ca, first_worker = (ca / "ca.pem").read_bytes(), (out / "worker.pem").read_bytes()
    run = _make(tmp_path / "more", "DNS:node2", ca)
    assert "reusing the CA" in run.stdout
    assert (ca / "ca.pem").read_bytes() == first_ca == (tmp_path / "more" / "ca.pem").read_bytes()
    assert (tmp_path / "more" / "worker.pem").read_bytes() != first_worker
    assert "OK" in _openssl("verify", "-CAfile", str(ca / "ca.pem"), str(tmp_path / "more" / "worker.pem"))
    assert not _private_keys(tmp_path / "more") or all(
        _public_of_key(k) != _public_of_key(ca / "ca-key.pem") for k in _private_keys(tmp_path / "more"))


@pytest.mark.parametrize("layout", ["ca inside output", "ca is output", "legacy key in output",
                                    "ca a symlink into output"])
def test_layouts_that_would_expose_the_ca_key_are_refused(tmp_path, layout):
    out = tmp_path / "tls"
    if layout == "legacy key in output":  # what the earlier script left there
        out.mkdir()
        (out / "ca-key.pem").write_text("-----BEGIN PRIVATE KEY-----\n")
        ca = tmp_path / "ca"
    elif layout == "ca a symlink into output":  # CA_DIR looks outside, but the key would land inside
        (out / "keys").mkdir(parents=True)
        ca = tmp_path / "ca-link"
        ca.symlink_to(out / "keys")
    else:
        ca = out / "ca" if layout == "ca inside output" else out
    run = _make(out, "DNS:localhost", ca, check=False)
    assert run.returncode == 2 and "make-certs.sh:" in run.stderr
    assert not [p for p in tmp_path.rglob("*.pem") if p.name != "ca-key.pem" or layout != "legacy key in output"]


def test_an_openssl_failure_is_reported_and_leaves_no_request_files(tmp_path):
    run = _make(tmp_path / "tls", "not-a-subject-alt-name", check=False)
    assert run.returncode == 1 and "openssl failed" in run.stderr and "subjectAltName" in run.stderr
    assert not list((tmp_path / "tls").glob("*.csr")) and not list((tmp_path / "tls").glob("*.ext"))


def _tree(folder: Path) -> dict:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_files_in_output_dir_it_did_not_write_are_never_deleted_nor_overwritten(tmp_path):
    """OUTPUT_DIR an existing directory holding the user's files: ``*.csr`` and ``*.ext`` of the user's used to be
    deleted by the script's clean-up (``rm -f OUT/*.csr OUT/*.ext``) and a ``client.pem`` of the user's overwritten.
    A file the script would write is now refused before anything is written; other files are kept."""
    out = tmp_path / "home"
    out.mkdir()
    (out / "mine.csr").write_text("the user's own request\n")
    (out / "notes.ext").write_text("the user's notes\n")
    (out / "client.pem").write_text("the user's own certificate\n")
    before = _tree(out)
    run = _make(out, "DNS:localhost", tmp_path / "ca", check=False)
    assert run.returncode == 2 and "already holds client.pem" in run.stderr and "never overwrites" in run.stderr
    assert _tree(out) == before
    (out / "client.pem").unlink()
    _make(out, "DNS:localhost", tmp_path / "ca")  # no clash left: the certificates are written beside the user's files
    assert (out / "mine.csr").read_text() == "the user's own request\n"
    assert (out / "notes.ext").read_text() == "the user's notes\n"
    assert sorted(p.name for p in out.iterdir()) == sorted(
        ["mine.csr", "notes.ext", "ca.pem", "dask-tls.yaml"] + [f"{r}{s}" for r in ("scheduler", "worker", "client")
                                                               for s in (".pem", "-key.pem")])


def test_a_second_run_into_the_same_output_dir_is_refused_and_changes_nothing(tmp_path):
    """Running the script again with the same OUTPUT_DIR used to replace every key and certificate of a
    cluster already set up (and, with another CA_DIR, its ca.pem: the other machines' certificates then
    no longer verify)."""
    out = tmp_path / "tls"
    _make(out)
    before = _tree(out)
    for ca in (None, tmp_path / "another-ca"):
        run = _make(out, "DNS:localhost", *([ca] if ca else []), check=False)
        assert run.returncode == 2 and "already holds ca.pem" in run.stderr, run.stderr
        assert _tree(out) == before
    assert not (tmp_path / "another-ca").exists()


def test_a_ca_dir_with_a_certificate_but_no_key_is_refused(tmp_path):
    ca = tmp_path / "ca"
    ca.mkdir()
    (ca / "ca.pem").write_text("the certificate of a CA whose key is elsewhere\n")
    run = _make(tmp_path / "tls", "DNS:localhost", ca, check=False)
    assert run.returncode == 2 and "holds ca.pem but no ca-key.pem" in run.stderr
    assert _tree(ca) == {"ca.pem": b"the certificate of a CA whose key is elsewhere\n"}
    assert not list((tmp_path / "tls").iterdir())


def test_a_failed_run_leaves_output_dir_as_it_was_and_can_be_run_again(tmp_path):
    """A bad SAN makes openssl fail after the CA and the first key are written: the keys and ca.pem it wrote in
    OUTPUT_DIR used to stay (and would now block the corrected run); they are removed, the user's file kept."""
    out = tmp_path / "tls"
    out.mkdir()
    (out / "README").write_text("the user's\n")
    run = _make(out, "not-a-subject-alt-name", check=False)
    assert run.returncode == 1 and "openssl failed" in run.stderr
    assert _tree(out) == {"README": b"the user's\n"}
    _make(out, "DNS:localhost")
    assert "worker.pem: OK" in _openssl("verify", "-CAfile", str(out / "ca.pem"), str(out / "worker.pem"))
