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
