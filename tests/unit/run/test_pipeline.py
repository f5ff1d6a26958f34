"""The runner's contract: manifests, skipping, reruns on change, interrupted runs."""

import json

import pytest

from retarget_cli.config import load_config
from retarget_cli.run.pipeline import ORDER, STAGES, manifest_path, run_pipeline, stage_params


def run(take, **kw):
    cfg = load_config(take / "config.yaml", stage_params())
    return cfg, {name: status for name, status, _ in run_pipeline(cfg, **kw)}


def test_every_stage_declares_outputs_and_a_runner_that_accepts_its_params():
    import inspect

    for name in ORDER:
        stage = STAGES[name]
        assert any(p.kind == "output" for p in stage.params), name
        accepted = inspect.signature(stage.runner).parameters
        for p in stage.params:
            assert p.name in accepted, f"{name}.{p.name} is declared but {stage.runner.__name__} does not take it"
        assert stage.help and all(p.help for p in stage.params), name


def test_every_stage_writes_a_manifest_with_hashes(small_take):
    # auto_pose needs a rig with landmark vertices: tests/e2e/test_real_rig.py runs it on the ICT rig.
    synthetic = [n for n in ORDER if n != "auto_pose"]
    cfg, status = run(small_take)
    assert set(status.values()) == {"ran"} and list(status) == synthetic
    for name in synthetic:
        man = json.loads(manifest_path(cfg, name).read_text())
        assert man["stage"] == name and man["outputs"] and man["inputs"]
        assert all(len(rec["sha256"]) == 64 for rec in [*man["inputs"].values(), *man["outputs"].values()])


def test_changes_rerun_exactly_the_affected_stages(small_take):
    run(small_take)
    _, status = run(small_take)
    assert set(status.values()) == {"skipped"}
    # The artist re-sculpts the target: pose and apply rerun, analysis does not.
    obj = small_take / "target" / "neutral.obj"
    obj.write_bytes(obj.read_bytes().replace(b"\nv ", b"\nv 0.5 ", 1))
    _, status = run(small_take)
    assert status == {"track": "skipped", "select": "skipped", "decompose": "skipped", "pose": "ran", "apply": "ran"}
    # A deleted output frame is noticed and regenerated.
    (small_take / "out" / "frames" / "frame_00007.obj").unlink()
    _, status = run(small_take)
    assert status["apply"] == "ran" and (small_take / "out" / "frames" / "frame_00007.obj").exists()


def test_rewritten_but_identical_input_does_not_rerun_downstream(small_take):
    run(small_take)
    # Rewriting the landmarks with the same bytes (new mtime) is not a change.
    lm = small_take / "out" / "landmarks.npz"
    lm.write_bytes(lm.read_bytes())
    _, status = run(small_take)
    assert set(status.values()) == {"skipped"}


def test_interrupted_stage_is_rerun_and_leaves_no_partial_file(small_take, monkeypatch):
    from retarget_cli.io import obj as objmod

    real = objmod.ObjMesh.to_bytes
    calls = {"n": 0}

    def dying(self, positions):
        calls["n"] += 1
        if calls["n"] == 30:
            raise KeyboardInterrupt
        return real(self, positions)

    monkeypatch.setattr(objmod.ObjMesh, "to_bytes", dying)
    cfg = load_config(small_take / "config.yaml", stage_params())
    with pytest.raises(KeyboardInterrupt):
        run_pipeline(cfg)
    assert not manifest_path(cfg, "apply").exists()
    assert not list((small_take / "out").rglob("*.part"))
    monkeypatch.setattr(objmod.ObjMesh, "to_bytes", real)
    _, status = run(small_take)
    assert status["apply"] == "ran" and status["track"] == "skipped"
    assert len(list((small_take / "out" / "frames").glob("frame_*.obj"))) == 60


def test_force_and_ranges(small_take):
    run(small_take)
    _, status = run(small_take, force=True, start="select", stop="decompose")
    assert status == {"select": "ran", "decompose": "ran"}


def test_code_fingerprint_covers_the_whole_package(monkeypatch):
    """A change anywhere in retarget_cli (a method, a stage), not only in run/, reruns the stages."""
    from pathlib import Path

    from retarget_cli.run import manifest

    seen, real = [], Path.read_bytes
    monkeypatch.setattr(Path, "read_bytes", lambda self: (seen.append(self), real(self))[1])
    manifest.code_fingerprint()
    folders = {p.parent.name for p in seen}
    assert {"methods", "stages", "io", "run"} <= folders, folders


def test_code_change_invalidates_manifests(small_take, monkeypatch):
    run(small_take)
    from retarget_cli.run import manifest

    monkeypatch.setattr(manifest, "code_fingerprint", lambda: "something-else")
    _, status = run(small_take)
    assert set(status.values()) == {"ran"}
