"""The README's specification example (section "Models") is what the README says it is: the TOML block,
read from README.md as written, is a valid specification whose every field is taken as written, its
commented defaults hold, the same fields in YAML give the same specification, omitting ``to_tube``
links to the ground, and the refusal quoted under it is the one a user gets."""

import pathlib
import re
import tomllib

import yaml

from tubeid.cli import main as cli
from tubeid.mechanics.spec import load_spec, spec_to_dict

REPO = pathlib.Path(__file__).resolve().parents[1]
MODELS = (REPO / "README.md").read_text().split("\n## Models\n", 1)[1].split("\n## ", 1)[0]


def _example() -> str:
    """The section's one TOML block."""
    blocks = re.findall(r"^```toml\n(.*?)^```", MODELS, re.S | re.M)
    assert len(blocks) == 1, f"expected one TOML block in the README's Models section, found {len(blocks)}"
    return blocks[0]


def _written(path: pathlib.Path, text: str) -> pathlib.Path:
    path.write_text(text)
    return path


def _taken_as_written(written, read, where="specification"):
    """Every field of ``written`` (parsed file) has the same value in ``read`` (the specification's plain form)."""
    if isinstance(written, dict):
        for key, value in written.items():
            assert key in read, f"{where}.{key} is written in the README but not part of the specification"
            _taken_as_written(value, read[key], f"{where}.{key}")
    elif isinstance(written, list):
        assert len(written) == len(read), f"{where}: {len(written)} entries written, {len(read)} read"
        for i, (w, r) in enumerate(zip(written, read)):
            _taken_as_written(w, r, f"{where}[{i}]")
    else:
        assert written == read, f"{where} = {written!r} in the README is read as {read!r}"


def test_the_example_specification_is_read_as_written(tmp_path, capsys):
    text = _example()
    spec = load_spec(_written(tmp_path / "my-bundle.toml", text))
    _taken_as_written(tomllib.loads(text), spec_to_dict(spec))
    # the defaults its comment states (`# ends = [...], damping_ratio = 0.02 by default`), for both tubes
    (comment,) = re.findall(r"#\s*(.*?) by default", text)
    defaults = {k: v for k, v in tomllib.loads(re.sub(r",\s*(?=\w+ = )", "\n", comment)).items()}
    assert set(defaults) == {"ends", "damping_ratio"}, comment
    for tube in spec_to_dict(spec)["tubes"]:
        assert {k: tube[k] for k in defaults} == defaults, f"tube {tube['name']}: the README's defaults {comment!r}"
    assert cli(["model", str(tmp_path / "my-bundle.toml")]) == 0
    assert re.search(r"^model\s+my-bundle$", capsys.readouterr().out, re.M)


def test_the_example_has_the_same_fields_in_yaml(tmp_path):
    text = _example()
    yaml_file = _written(tmp_path / "my-bundle.yaml", yaml.safe_dump(tomllib.loads(text), sort_keys=False))
    assert load_spec(yaml_file) == load_spec(_written(tmp_path / "my-bundle.toml", text))


def test_a_link_without_to_tube_goes_to_the_ground(tmp_path):
    text = _example()
    ground = re.sub(r'^to_tube = "centre"\n', "", text, flags=re.M)
    assert ground != text, "the README's link no longer names to_tube = \"centre\""
    (link,) = load_spec(_written(tmp_path / "ground.toml", ground)).links
    assert link.tube == "outer" and link.to_tube is None


def test_the_quoted_refusal_is_the_one_given(tmp_path, capsys):
    """The README quotes the message for a stop off its tube; the example with that stop gives it verbatim."""
    (quoted,) = re.findall(r"`(tubeid: error: stops\[0\]\.x = 17\.0: [^`]*)`", MODELS)
    text = _example()
    bad = re.sub(r'(\[\[stops\]\]\ntube = "centre"\n)x = 6\.0\n', r"\1x = 17.0\n", text)
    assert bad != text, "the README's stop is no longer at x = 6.0 on 'centre'"
    assert cli(["model", str(_written(tmp_path / "bad.toml", bad))]) == 2
    assert capsys.readouterr().err.strip() == quoted
