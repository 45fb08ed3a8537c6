"""Output directories with a manifest: tubeid replaces or removes only what it wrote and can prove it wrote."""

import json
import multiprocessing
import os

import pytest

from tubeid._outputs import MANIFEST_NAME, OutputDir, file_sha256
from tubeid.errors import SpecificationError


def test_writes_are_recorded_with_their_checksum(tmp_path):
    out = OutputDir(tmp_path / "rep")
    p = out.write_text("summary.md", "hello")
    assert p.read_text() == "hello"
    e = out.entries()["summary.md"]
    assert e["kind"] == "file" and e["size"] == 5 and e["sha256"] == file_sha256(p)
    assert json.loads((tmp_path / "rep" / MANIFEST_NAME).read_text())["entries"]["summary.md"]["sha256"] == e["sha256"]
    out.write_text("summary.md", "hello again")  # ours, unchanged since: may be replaced
    assert p.read_text() == "hello again" and out.owned("summary.md")


def test_a_user_file_named_like_an_output_is_never_overwritten_or_removed(tmp_path):
    (tmp_path / "summary.md").write_text("my notes")
    out = OutputDir(tmp_path)
    with pytest.raises(SpecificationError, match=r"summary.md.*not written by tubeid"):
        out.write_text("summary.md", "report")
    assert (tmp_path / "summary.md").read_text() == "my notes"
    out.write_text("other.md", "x")
    assert out.remove() == []
    assert (tmp_path / "summary.md").read_text() == "my notes"
    assert not (tmp_path / "other.md").exists()


def test_a_file_edited_after_tubeid_wrote_it_is_the_users(tmp_path):
    out = OutputDir(tmp_path)
    out.write_text("report.md", "generated")
    (tmp_path / "report.md").write_text("generated, then annotated by hand")
    assert not out.owned("report.md")
    with pytest.raises(SpecificationError, match="changed since"):
        out.write_text("report.md", "regenerated")
    assert out.remove() == ["report.md"]
    assert (tmp_path / "report.md").read_text() == "generated, then annotated by hand"


def test_same_size_edit_is_detected_by_content(tmp_path):
    out = OutputDir(tmp_path)
    out.write_text("a.txt", "abc")
    (tmp_path / "a.txt").write_text("abd")
    assert not out.owned("a.txt")


def test_names_must_stay_inside_the_directory(tmp_path):
    out = OutputDir(tmp_path / "o")
    for bad in ("../x", "/etc/passwd", "a/b", MANIFEST_NAME):
        with pytest.raises(SpecificationError, match="plain file name"):
            out.write_text(bad, "x")


def test_directories_are_recorded_not_removed(tmp_path):
    out = OutputDir(tmp_path)
    out.record_directory("diagnose.zarr")
    (tmp_path / "diagnose.zarr").mkdir()
    assert out.owned("diagnose.zarr")
    out.remove()
    assert (tmp_path / "diagnose.zarr").is_dir()
    (tmp_path / "theirs.zarr").mkdir()
    with pytest.raises(SpecificationError, match="not created by tubeid"):
        out.record_directory("theirs.zarr")


def test_a_corrupt_manifest_makes_tubeid_touch_nothing(tmp_path):
    (tmp_path / "summary.md").write_text("x")
    (tmp_path / MANIFEST_NAME).write_text("{not json")
    with pytest.raises(SpecificationError, match="not a tubeid manifest"):
        OutputDir(tmp_path).remove()
    assert (tmp_path / "summary.md").exists()


def test_not_a_directory_and_not_writable(tmp_path):
    (tmp_path / "f").write_text("x")
    with pytest.raises(SpecificationError, match="not a directory"):
        OutputDir(tmp_path / "f")
    if os.geteuid() != 0:  # root writes anywhere
        ro = tmp_path / "ro"
        ro.mkdir()
        ro.chmod(0o500)
        with pytest.raises(SpecificationError, match="not writable"):
            OutputDir(ro)


def _writer(path, k):
    out = OutputDir(path)
    for i in range(20):
        out.write_text(f"f{k}-{i}.txt", str(i))


def test_concurrent_writers_lose_no_manifest_entry(tmp_path):
    ctx = multiprocessing.get_context("spawn")
    procs = [ctx.Process(target=_writer, args=(tmp_path, k)) for k in range(3)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(60)
    assert all(p.exitcode == 0 for p in procs)
    assert len(OutputDir(tmp_path).entries()) == 60


@pytest.mark.parametrize("entry", ["../victim.txt", "absolute", "sub/victim.txt"])
def test_a_manifest_naming_a_file_outside_the_directory_removes_nothing(tmp_path, entry):
    """An edited manifest is no proof, even with the file's true checksum: tubeid records plain names only."""
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "victim.txt").write_text("precious")
    out = OutputDir(tmp_path / "out")
    out.write_text("report.md", "x")
    name = str(victim) if entry == "absolute" else entry
    target = tmp_path / "out" / name if entry != "absolute" else victim
    manifest = json.loads((tmp_path / "out" / MANIFEST_NAME).read_text())
    manifest["entries"][name] = {"kind": "file", "sha256": file_sha256(target if target.exists() else victim),
                                 "size": 8, "written": "then"}
    (tmp_path / "out" / MANIFEST_NAME).write_text(json.dumps(manifest))
    with pytest.raises(SpecificationError, match="not plain file names"):
        out.remove()
    assert victim.read_text() == "precious" and (tmp_path / "sub" / "victim.txt").read_text() == "precious"
    assert (tmp_path / "out" / "report.md").read_text() == "x"


def test_only_tubeids_own_temporaries_are_removed_by_their_exact_name(tmp_path):
    """A write killed before its rename leaves ``.tubeid-tmp-`` + 8 characters of [a-z0-9_] (``mkstemp``'s
    form): removed. A user's files that merely start with ``.tubeid-tmp-`` (longer, shorter, other
    characters, a directory of that form) are theirs: kept byte for byte."""
    import tempfile

    out = OutputDir(tmp_path)
    out.write_text("report.md", "x")
    fd, ours = tempfile.mkstemp(prefix=".tubeid-tmp-", dir=tmp_path)  # as _atomic_write makes it
    os.close(fd)
    users = [".tubeid-tmp-notes.txt", ".tubeid-tmp-abc", ".tubeid-tmp-ABCDEFGH", ".tubeid-tmp-abcdefgh1"]
    for name in users:
        (tmp_path / name).write_text("my notes")
    (tmp_path / ".tubeid-tmp-dir_1234").mkdir()
    assert out.remove() == []
    assert not os.path.exists(ours) and not (tmp_path / "report.md").exists()
    for name in users:
        assert (tmp_path / name).read_text() == "my notes", name
    assert (tmp_path / ".tubeid-tmp-dir_1234").is_dir()


def test_removal_is_a_dry_run_of_remove(tmp_path):
    out = OutputDir(tmp_path)
    out.write_text("a.md", "a")
    out.write_text("b.md", "b")
    (tmp_path / "b.md").write_text("edited")
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    assert out.removal() == (["a.md"], ["b.md"])
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before  # nothing removed or rewritten
    assert out.remove() == ["b.md"] and not (tmp_path / "a.md").exists()
