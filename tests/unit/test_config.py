import re

import pytest

from retarget_cli.config import load_config
from retarget_cli.errors import ConfigError
from retarget_cli.run.pipeline import STAGES, resolve, stage_params


def write(tmp_path, text):
    p = tmp_path / "config.yaml"
    p.write_text(text)
    return p


def test_valid_config_resolves_paths_and_links(tmp_path):
    p = write(tmp_path, "output_dir: out\ntrack: {video: v.mp4, init: v.pts}\nselect: {k: 4}\ndecompose: {}\n")
    cfg = load_config(p, stage_params())
    assert cfg.output_dir == (tmp_path / "out").resolve()
    kw = resolve(cfg, "decompose")
    assert kw["landmarks"] == cfg.output_dir / "landmarks.npz"
    assert kw["keys"] == cfg.output_dir / "keys.json"
    assert resolve(cfg, "track")["video"] == tmp_path.resolve() / "v.mp4"
    assert resolve(cfg, "select")["k"] == 4


@pytest.mark.parametrize(
    "text, message",
    [
        ("selct: {k: 3}\n", r"config.yaml: unknown key 'selct'; did you mean 'select'\?"),
        ("select: {kk: 3}\n", r"config.yaml: select: unknown key 'kk'; did you mean 'k'\?"),
        ("select: {k: 0}\n", r"select.k: 0 is out of range; expected int in \[1, 1000\]"),
        ("select: {k: 2.5}\n", r"select.k: expected an integer"),
        ("decompose: {solver: nnl}\n", r"decompose.solver: 'nnl' is not one of nnls, ls, bounded, .*; did you mean 'nnls'\?"),
        ("track: {anchor: 3}\n", r"track.anchor: expected true or false"),
        ("- a\n- b\n", r"expected a mapping"),
        ("select: [1, 2\n", r"config.yaml:\d+: invalid YAML"),
    ],
)
def test_bad_configs_name_the_file_and_key(tmp_path, text, message):
    with pytest.raises(ConfigError, match=message):
        load_config(write(tmp_path, text), stage_params())


def test_missing_required_input_is_named(tmp_path):
    cfg = load_config(write(tmp_path, "select: {k: 3}\n"), stage_params())
    with pytest.raises(ConfigError, match=r"select.landmarks is required \(or add a 'track' section\)"):
        resolve(cfg, "select")


def test_overrides_take_precedence_and_are_validated(tmp_path):
    p = write(tmp_path, "select: {k: 3, landmarks: l.npz}\n")
    assert load_config(p, stage_params(), ["select.k=7"]).sections["select"]["k"] == 7
    with pytest.raises(ConfigError, match="did you mean 'select'"):
        load_config(p, stage_params(), ["selec.k=7"])
    with pytest.raises(ConfigError, match="STAGE.KEY=VALUE"):
        load_config(p, stage_params(), ["k=7"])


def test_every_stage_param_default_passes_its_own_check():
    for stage in STAGES.values():
        for p in stage.params:
            if not p.required:
                assert p.check(p.default, f"{stage.name}.{p.name}") == p.default


@pytest.mark.parametrize("kind, text", [
    ("config", "select: {k: 16, regions: {mouth: null}}\nselect: {k: 4}\n"),
    ("rig", "neutral: n.obj\nshapes: {jawOpen: a.obj, jawOpen: b.obj}\n"),
    ("targets", "version: 1\nversion: 1\n"),
    ("edits", "edits:\n  - pin: {frames: 3, frames: 4}\n"),
    ("shots", "shots:\n  - {name: a, config: c.yaml}\nshots: []\n"),
])
def test_a_key_given_twice_is_refused_in_every_yaml_kind(tmp_path, kind, text):
    """PyYAML keeps the last of two equal keys silently (a second select: section replaced the first)."""
    from retarget_cli.batch.plan import load_plan
    from retarget_cli.config import load_config
    from retarget_cli.errors import RetargetError
    from retarget_cli.io.editfiles import read_edits
    from retarget_cli.io.rig import read_rig
    from retarget_cli.io.stagefiles import read_targets
    from retarget_cli.run.pipeline import stage_params

    path = tmp_path / f"{kind}.yaml"
    path.write_text(text)
    read = {"config": lambda p: load_config(p, stage_params()), "rig": read_rig, "targets": read_targets,
            "edits": lambda p: read_edits(p, n_vertices=10, frames=list(range(10))),
            "shots": load_plan}[kind]
    with pytest.raises(RetargetError) as err:
        read(path)
    msg = str(err.value)
    assert "\n" not in msg and f"{path}:" in msg and "given twice" in msg, msg


_BAD_YAML = [
    ("select: [1, 2\n", r"f\.yaml:2: invalid YAML \(.* at line 2, column 1\)$"),
    ("version: 1\nn_points: 68\n{\n1 2\n", r"f\.yaml:4: invalid YAML \(.* at line 4, column 1\)$"),
    ("a: b: c\n", r"f\.yaml:1: invalid YAML \(mapping values are not allowed .* at line 1, column 5\)$"),
    ("- a\nb: c\n", r"f\.yaml:2: invalid YAML \(.* at line 2, column 1\)$"),
    ("a: *x\n", r"f\.yaml:1: invalid YAML \(found undefined alias.* at line 1, column 4\)$"),
    ("a: !!python/object:os.system x\n", r"f\.yaml:1: invalid YAML \(could not determine a constructor .*\)$"),
    ("\t- a\n", r"f\.yaml:1: invalid YAML \(found character .*that cannot start any token at line 1, column 1\)$"),
    ("a: [1,\n\x00", r"f\.yaml: invalid YAML \(unacceptable character #x0000: .*\)$"),
    ("a: \ud800\n", r"f\.yaml: invalid YAML \(unacceptable character #xd800: .*\)$"),
    ("a: 1\n---\nb: 2\n", r"f\.yaml:2: invalid YAML \(but found another document at line 2, column 1\)$"),
    ("x:\n  b: 1\n  c: 2\n  b: 3\n", r"f\.yaml:4: key 'b' given twice in one mapping \(first at line 2\)"),
    ("a: &a [1]\n" + "".join(f"x{i}: &x{i} [*{'a' if i == 0 else f'x{i - 1}'}, *{'a' if i == 0 else f'x{i - 1}'}]\n"
                             for i in range(30)), r"f\.yaml: the YAML document expands to more than 1000000 values"),
    ("a: &a 1\nb: [" + ", ".join(["*a"] * 1001) + "]\n", r"f\.yaml: more than 1000 YAML aliases"),
    ("[" * 2000 + "]" * 2000, r"f\.yaml(:1: invalid YAML \(exceeded maximum nesting depth.*|: the YAML document is "
                              r"nested too deeply)$"),
]


def _loaders():
    import yaml

    return [yaml.SafeLoader] + ([yaml.CSafeLoader] if getattr(yaml, "__with_libyaml__", False) else [])


@pytest.mark.parametrize("loader", _loaders(), ids=lambda c: c.__name__)
@pytest.mark.parametrize("text, message", _BAD_YAML)
def test_bad_yaml_is_one_line_with_its_line_on_both_loaders(monkeypatch, loader, text, message):
    """libyaml (CSafeLoader, used when PyYAML has it) words some problems differently from the pure-Python
    loader; the message keeps its form: the file, the line, one line."""
    from retarget_cli import config

    monkeypatch.setattr(config, "yaml_loader", lambda: loader)
    with pytest.raises(ConfigError) as err:
        config.load_yaml(text, "f.yaml", with_line=True)
    assert "\n" not in str(err.value) and re.match(message, str(err.value)), str(err.value)


def test_both_yaml_loaders_read_the_same_values(monkeypatch):
    from retarget_cli import config

    text = ("a: 2001-01-01\nb: 0o17\nc: 1_000\nd: .inf\ne: yes\nf: 0x1F\ng: ~\nh: 1e3\ni: '1'\nj: !!binary aGVsbG8=\n"
            "k: &k [1, 2]\nl: *k\nm: {<<: {d: 1}, d: 2}\nn: [-.5, +3, 1.5e+3, null, NO]\n")
    got = []
    for loader in _loaders():
        monkeypatch.setattr(config, "yaml_loader", lambda loader=loader: loader)
        got.append(config.load_yaml(text, "f.yaml"))
    assert got[0]["l"] == [1, 2] and got[0]["m"] == {"d": 2} and got[0]["j"] == b"hello"
    assert all(g == got[0] and repr(g) == repr(got[0]) for g in got)
