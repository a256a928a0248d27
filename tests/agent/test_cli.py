"""The command line: the quick-look render and one-line errors."""

import subprocess
import sys

from agent.cli import main


def test_sim_render_writes_image_labels_and_overlay(tmp_path):
    rc = main(["-q", "sim", "render", "--altitude", "15", "--radius", "10", "--pitch", "-60",
               "--width", "96", "--height", "72", "--supersample", "2", "--texture-size", "512",
               "--out", str(tmp_path)])
    assert rc == 0
    for name in ("view.png", "view.txt", "view_boxes.png", "classes.txt", "camera.json"):
        assert (tmp_path / name).is_file()
    assert (tmp_path / "classes.txt").read_text().split() == ["standing", "kneeling", "prone"]


def test_bad_input_is_one_line_and_nonzero(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "agent.cli", "sim", "render", "--pitch", "120",
                           "--out", str(tmp_path)], capture_output=True, text=True)
    assert proc.returncode == 2
    assert proc.stderr.strip().count("\n") == 0
    assert "pitch" in proc.stderr


def test_unknown_benchmark_is_a_clear_error(capsys):
    assert main(["bench", "no-such-benchmark"]) == 2
    assert "no benchmark" in capsys.readouterr().err
