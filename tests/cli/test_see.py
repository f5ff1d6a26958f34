"""render, preview and report: the commands that show a run."""

import json
import shutil
from html.parser import HTMLParser

import numpy as np
import pytest
from click.testing import CliRunner

from retarget_cli.cli.commands import main

cv2 = pytest.importorskip("cv2")


@pytest.fixture(scope="module")
def ran_take(small_take_template, tmp_path_factory):
    """The 60-frame synthetic take (192x192) run through the whole pipeline once for this module."""
    d = tmp_path_factory.mktemp("see") / "take"
    shutil.copytree(small_take_template, d)
    result = CliRunner().invoke(main, ["-q", "run", str(d / "config.yaml")])
    assert result.exit_code == 0, result.output
    return d


def video_info(path):
    cap = cv2.VideoCapture(str(path))
    n = 0
    size = None
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        n += 1
        size = (frame.shape[1], frame.shape[0])
    cap.release()
    return n, size


def test_manifests_record_stage_seconds(ran_take):
    for stage in ("track", "select", "decompose", "pose", "apply"):
        man = json.loads((ran_take / "out" / ".retarget" / f"{stage}.json").read_text())
        assert isinstance(man["seconds"], float) and man["seconds"] >= 0


# --------------------------------------------------------------------------- render


def test_render_one_obj_to_png(ran_take, tmp_path):
    out = tmp_path / "neutral.png"
    result = CliRunner().invoke(main, ["render", str(ran_take / "target" / "neutral.obj"), "-o", str(out),
                                       "--size", "200x150"])
    assert result.exit_code == 0, result.output
    img = cv2.imread(str(out))
    assert img.shape == (150, 200, 3)
    bg = img[0, 0].astype(int)
    assert (np.abs(img.astype(int) - bg).sum(-1) > 30).mean() > 0.15  # the mesh covers part of the image


def test_render_sequence_to_video_and_refuses_png_for_many(ran_take, tmp_path):
    frames = ran_take / "out" / "frames"
    out = tmp_path / "seq.mp4"
    result = CliRunner().invoke(main, ["render", str(frames), "-o", str(out), "--size", "96", "--fov", "0"])
    assert result.exit_code == 0, result.output
    assert video_info(out) == (60, (96, 96))
    result = CliRunner().invoke(main, ["render", str(frames / "frame_0000*.obj"), "-o", str(tmp_path / "x.png")])
    assert result.exit_code == 1
    assert "10 meshes need a video output" in result.stderr
    result = CliRunner().invoke(main, ["render", str(tmp_path / "none.obj"), "-o", str(tmp_path / "x.png")])
    assert result.exit_code == 1 and "none.obj" in result.stderr


# --------------------------------------------------------------------------- preview


def test_preview_has_the_right_frame_count_and_size(ran_take, tmp_path):
    out = tmp_path / "preview.mp4"
    result = CliRunner().invoke(main, ["preview", str(ran_take / "config.yaml"), "-o", str(out),
                                       "--frames", "5:17", "--size", "96"])
    assert result.exit_code == 0, result.output
    # panels: source 96 (192x192 scaled to height 96) + mesh 96 + weight bars max(0.9 * 96, 200) = 392 wide
    assert video_info(out) == (12, (392, 96))


def test_preview_of_a_run_directory_without_video(ran_take, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(ran_take / "out", run)  # the track manifest's video path no longer resolves from here
    out = tmp_path / "p.avi"
    result = CliRunner().invoke(main, ["preview", str(run), "-o", str(out), "--size", "64"])
    assert result.exit_code == 0, result.output
    n, size = video_info(out)
    assert n == 60 and size[1] == 64


def test_preview_source_panel_shows_the_video_with_landmarks(ran_take):
    from retarget_cli.run.runfiles import locate_run
    from retarget_cli.see.preview import RunData, confidence_color, preview_frames

    data = RunData(locate_run(ran_take / "config.yaml"))
    img = next(preview_frames(data, range(3, 4), height=192))  # the take is 192x192: no scaling
    cap = cv2.VideoCapture(str(ran_take / "face.mp4"))
    for _ in range(4):
        ok, src = cap.read()
    cap.release()
    # a landmark of frame 3 is drawn in its confidence colour at its position
    x, y = np.round(data.lm.points[3, 30]).astype(int)
    expected = confidence_color(data.lm.confidence[3, 30:31])[0].astype(int)
    assert np.abs(img[y, x].astype(int) - expected).max() <= 40
    # away from the landmarks and the text lines, the panel is the video frame
    yy, xx = np.mgrid[0:192, 0:192]
    d = np.min(np.hypot(xx[..., None] - data.lm.points[3, :, 0], yy[..., None] - data.lm.points[3, :, 1]), -1)
    far = (d > 6) & (yy > 26) & (yy < 170)
    assert np.abs(img[:192, :192][far].astype(int) - src[far].astype(int)).mean() < 1.0


def test_preview_to_an_image_is_that_image_type_and_holds_one_frame(ran_take, tmp_path):
    from retarget_cli.run.runfiles import locate_run
    from retarget_cli.see.preview import RunData, preview_frames

    png, jpg = tmp_path / "f7.png", tmp_path / "f7.jpg"
    for out in (png, jpg):
        result = CliRunner().invoke(main, ["preview", str(ran_take / "config.yaml"), "-o", str(out),
                                           "--frames", "7", "--size", "96"])
        assert result.exit_code == 0, result.output
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"  # a real PNG, not JPEG bytes under a .png name
    assert jpg.read_bytes()[:3] == b"\xff\xd8\xff"
    # the PNG is lossless: its source and weight panels are frame 7's, pixel for pixel (the mesh panel's
    # camera is the command's), and the mesh panel holds the character
    want = next(preview_frames(RunData(locate_run(ran_take / "config.yaml")), range(7, 8), height=96))
    got = cv2.imread(str(png))
    assert got.shape == want.shape == (96, 392, 3)
    assert np.array_equal(got[:, :96], want[:, :96]) and np.array_equal(got[:, 192:], want[:, 192:])
    assert np.array_equal(cv2.imread(str(jpg)).shape, want.shape)
    assert got[:, 96:192].std() > 5
    # many frames into one image: refused in one line, nothing written
    many = tmp_path / "many.png"
    result = CliRunner().invoke(main, ["preview", str(ran_take / "config.yaml"), "-o", str(many),
                                       "--frames", "5:17", "--size", "96"])
    assert result.exit_code == 2 and "holds one frame, but 12 are selected" in result.output
    assert not many.exists() and "Traceback" not in result.output
    bad = tmp_path / "p.xyz"
    result = CliRunner().invoke(main, ["preview", str(ran_take / "config.yaml"), "-o", str(bad)])
    assert result.exit_code == 1 and "unknown output type '.xyz'" in result.output and not bad.exists()


def test_preview_rejects_an_empty_frame_range(ran_take, tmp_path):
    result = CliRunner().invoke(main, ["preview", str(ran_take / "config.yaml"), "-o", str(tmp_path / "p.mp4"),
                                       "--frames", "100:200"])
    assert result.exit_code == 2
    assert "selects no frame of the 60-frame take" in result.output


# --------------------------------------------------------------------------- report

VOID = {"meta", "img", "br", "hr", "link", "input", "col", "area", "base", "wbr", "source"}


class Checker(HTMLParser):
    """Strict enough for our output: every non-void tag closed in order; collects refs and sections."""

    def __init__(self):
        super().__init__(convert_charrefs=True)
        self.stack, self.errors, self.refs = [], [], []
        self.sections = {}  # id -> number of <figure>
        self.current = None
        self.doctype = False

    def handle_decl(self, decl):
        self.doctype = decl.lower() == "doctype html"

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        for k in ("src", "href", "srcset", "data", "action", "poster"):
            if k in a:
                self.refs.append((tag, k, a[k]))
        if "style" in a and "url(" in a["style"]:
            self.refs.append((tag, "style", a["style"]))
        if tag == "section":
            self.current = a.get("id")
            self.sections[self.current] = 0
        if tag == "figure" and self.current is not None:
            self.sections[self.current] += 1
        if tag not in VOID:
            self.stack.append(tag)

    def handle_endtag(self, tag):
        if tag in VOID:
            return
        if not self.stack or self.stack[-1] != tag:
            self.errors.append(f"unexpected </{tag}>, open: {self.stack[-3:]}")
            return
        self.stack.pop()
        if tag == "section":
            self.current = None


def check_html(text):
    c = Checker()
    c.feed(text)
    c.close()
    assert c.doctype
    assert not c.errors and not c.stack, (c.errors, c.stack)
    for tag, attr, value in c.refs:
        if attr == "href":
            assert value.startswith("#"), (tag, attr, value[:80])
        else:
            assert value.startswith("data:image/png;base64,"), (tag, attr, value[:80])
    assert "<script" not in text.lower() and "@import" not in text and "url(" not in text
    return c


def test_report_is_self_contained_valid_html_with_one_figure_per_section(ran_take, tmp_path):
    out = tmp_path / "report.html"
    result = CliRunner().invoke(main, ["report", str(ran_take / "config.yaml"), "-o", str(out)])
    assert result.exit_code == 0, result.output
    text = out.read_text(encoding="utf-8")
    c = check_html(text)
    # every section with data; no E-vs-k curve in this run, so it is omitted; decompose's
    # per-frame cardinality (weights.npz <region>_cardinality) fills the cardinality section
    # the take is synthetic (truth.npz beside the video): the truth section too
    assert c.sections == {"summary": 1, "tracking": 1, "rest": 1, "keys": 1, "weights": 1, "residuals": 1,
                          "rig": 1, "truth": 1}
    assert "Worst frames" in text and "source frame" in text and "target frame" in text
    # deterministic: same run, same bytes
    out2 = tmp_path / "again.html"
    assert CliRunner().invoke(main, ["report", str(ran_take / "config.yaml"), "-o", str(out2)]).exit_code == 0
    assert out2.read_bytes() == out.read_bytes()


def test_report_adds_curve_and_rig_sections_when_their_data_exists(ran_take, tmp_path):
    from retarget_cli.io.atomic import savez

    run = tmp_path / "run"
    shutil.copytree(ran_take / "out", run)
    rows = ["region,method,k,E"] + [f"{r},{m},{k},{100 / k * (1.3 if m == 'kmeans' else 1):.3f}"
                                    for r in ("brows-eyes", "mouth") for m in ("pca-extremes", "kmeans")
                                    for k in range(2, 13)]
    (run / "select_curve.csv").write_text("\n".join(rows) + "\n")
    savez(run / "rig_weights.npz", {"weights": np.zeros((60, 8)), "cardinality": np.arange(60) % 5,
                                    "objective": np.linspace(1, 0.1, 60)})
    out = tmp_path / "report.html"
    result = CliRunner().invoke(main, ["report", str(run), "-o", str(out)])
    assert result.exit_code == 0, result.output
    c = check_html(out.read_text(encoding="utf-8"))
    # the copied run finds its video where its config's folder (the manifests' base) still has it, and the truth
    # beside it
    assert c.sections == {"summary": 1, "tracking": 1, "rest": 1, "keys": 1, "curve": 1, "weights": 1,
                          "residuals": 1, "rig": 1, "truth": 1}
    (ran_take / "face.mp4").rename(ran_take / "face.moved.mp4")  # gone from there too: neither
    try:
        result = CliRunner().invoke(main, ["report", str(run), "-o", str(out)])
    finally:
        (ran_take / "face.moved.mp4").rename(ran_take / "face.mp4")
    assert result.exit_code == 0, result.output
    assert "was not found" in result.stderr and "--video" in result.stderr
    assert check_html(out.read_text(encoding="utf-8")).sections == {
        "summary": 1, "tracking": 1, "rest": 1, "keys": 1, "curve": 1, "weights": 1, "residuals": 1, "rig": 1}


def test_report_of_weights_alone_omits_what_is_missing(ran_take, tmp_path):
    run = tmp_path / "bare"
    run.mkdir()
    shutil.copy(ran_take / "out" / "weights.npz", run)
    out = tmp_path / "r.html"
    result = CliRunner().invoke(main, ["report", str(run), "-o", str(out)])
    assert result.exit_code == 0, result.output
    text = out.read_text(encoding="utf-8")
    c = check_html(text)
    # no manifests (so no timings figure), no landmarks, no keys.json (keys come from weights.npz), no frames
    assert c.sections == {"summary": 0, "keys": 1, "weights": 1, "residuals": 1, "rig": 1}
    assert "No stage manifests" in text


def _truth_row(text, label):
    """The cells of the truth section's row *label* (HTML tags stripped)."""
    import re

    sec = text[text.index('id="truth"'):]
    row = re.search(r"<tr><td>" + re.escape(label) + r"</td>(.*?)</tr>", sec).group(1)
    return [re.sub(r"<[^>]+>", "", c) for c in re.findall(r"<td[^>]*>(.*?)</td>", row)]


def test_report_measures_the_run_against_the_synthetic_truth(ran_take, tmp_path):
    from retarget_cli.io.atomic import load_npz, savez
    from retarget_cli.io.obj import read_obj

    out = tmp_path / "report.html"
    assert CliRunner().invoke(main, ["report", str(ran_take / "config.yaml"), "-o", str(out)]).exit_code == 0
    cells = _truth_row(out.read_text(encoding="utf-8"), "target mesh (apply&#x27;s frames)")
    # independently: the frames against truth.npz's target
    got = np.stack([read_obj(f).vertices for f in sorted((ran_take / "out" / "frames").glob("frame_*.obj"))])
    truth = load_npz(ran_take / "truth.npz")["target"].astype(np.float64)
    err = np.linalg.norm(got - truth, axis=2).mean()
    pct = 100 * err / np.linalg.norm(truth - truth[:1], axis=2).mean()
    assert cells[0] == f"{err:.4g} ({pct:.1f} % of the mean true displacement)"
    assert 0 < pct < 50  # the pipeline follows the synthetic face
    ratio = float(cells[3].rstrip("×"))
    assert 0.3 < ratio < 3.0
    # a truth equal to the run's own frames: no error, jitter ratio 1
    same = tmp_path / "same.npz"
    savez(same, {"target": got.astype(np.float32)})
    out2 = tmp_path / "same.html"
    assert CliRunner().invoke(main, ["report", str(ran_take / "config.yaml"), "-o", str(out2),
                                     "--truth", str(same)]).exit_code == 0
    cells = _truth_row(out2.read_text(encoding="utf-8"), "target mesh (apply&#x27;s frames)")
    assert float(cells[0].split()[0]) < 1e-6 and "(0.0 %" in cells[0] and cells[3] == "1.00×"


def test_report_refuses_a_truth_file_without_the_true_animation(ran_take, tmp_path):
    from retarget_cli.io.atomic import savez

    bad = tmp_path / "truth.npz"
    savez(bad, {"curves": np.zeros((60, 8))})
    out = tmp_path / "r.html"
    result = CliRunner().invoke(main, ["report", str(ran_take / "config.yaml"), "-o", str(out), "--truth", str(bad)])
    assert result.exit_code == 1
    msg = result.stderr.strip()
    assert "\n" not in msg and str(bad) in msg and "'target'" in msg
    assert not out.exists()


def test_report_without_matplotlib_says_how_to_install_it(ran_take, tmp_path, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "matplotlib", None)  # makes `import matplotlib` raise ImportError
    result = CliRunner().invoke(main, ["report", str(ran_take / "config.yaml"), "-o", str(tmp_path / "r.html")])
    assert result.exit_code == 1
    assert "pip install 'retarget[report]'" in result.stderr
    assert not (tmp_path / "r.html").exists()


def test_report_and_preview_need_a_run(tmp_path):
    result = CliRunner().invoke(main, ["report", str(tmp_path), "-o", str(tmp_path / "r.html")])
    assert result.exit_code == 1
    assert "no landmarks.npz, weights.npz or frames" in result.stderr


def test_jitter_and_worst_frames():
    from retarget_cli.see.report import jitter_per_frame, worst_frames

    W = np.zeros((10, 2))
    W[5, 0] = 1.0
    j = jitter_per_frame(W)
    np.testing.assert_allclose(j, [0, 0, 0, 0, 0.5, 2.0, 0.5, 0, 0, 0])
    assert worst_frames(j, 2, suppress=1) == [5]  # neighbours suppressed, zero jitter never listed
    assert worst_frames(j, 3, suppress=0) == [5, 4, 6]  # ties go to the earlier frame
    assert worst_frames(np.array([1.0, 5, 4, 0, 3]), 3, suppress=1) == [1, 4]


def test_curve_csv_layouts(tmp_path):
    from retarget_cli.see.report import read_curve

    p = tmp_path / "c.csv"
    p.write_text("k,pca-extremes,greedy\n2,10,8\n3,6,4\n")
    assert sorted(read_curve(p)[""]) == ["greedy", "pca-extremes"]
    p.write_text("region,method,k,E\nmouth,greedy,3,4\nmouth,greedy,2,8\n")
    k, e = read_curve(p)["mouth"]["greedy"]
    np.testing.assert_array_equal(k, [2, 3])
    np.testing.assert_array_equal(e, [8, 4])
