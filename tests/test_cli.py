"""The kinreg command through its entry point: outputs, exit codes, one-line errors."""

import subprocess
import sys

import numpy as np
import tomllib
from clirunner import run_cli

from kinreg.io.e57 import E57CloudReader


def test_version(capsys):
    code, out, _ = run_cli(["--version"], capsys)
    assert code == 0 and out.startswith("kinreg 0.")


def test_info_trajectory_and_cloud(synthetic_run, capsys):
    code, out, _ = run_cli(["info", synthetic_run.trajectory_path], capsys)
    assert code == 0 and "3,001" in out and "path length" in out
    code, out, _ = run_cli(["info", synthetic_run.cloud_path, "--full"], capsys)
    assert code == 0 and "60,000" in out and "gps_time" in out and "time-sorted" in out


def test_slice_writes_a_sequence_that_reproduces_the_cloud(synthetic_run, tmp_path, capsys):
    out_path = tmp_path / "out" / "seq.e57"
    code, out, err = run_cli(["slice", "-t", synthetic_run.trajectory_path, "-c", synthetic_run.cloud_path,
                              "-o", out_path, "--window-s", "5"], capsys)
    assert code == 0, err
    assert "6" in out and out_path.exists()
    with E57CloudReader(out_path) as reader:
        assert reader.info.n_scans == 6
        xyz = np.concatenate([c.xyz for c in reader.iter_chunks()])
        t = np.concatenate([c.stamps_s for c in reader.iter_chunks()])
    order = np.argsort(t, kind="stable")
    np.testing.assert_array_equal(t[order], synthetic_run.stamps_s)
    assert np.max(np.abs(xyz[order] - synthetic_run.xyz)) < 1e-4
    assert sorted(p.name for p in out_path.parent.iterdir()) == ["seq.e57"]  # no temporary left


def test_existing_output_is_refused_and_kept(synthetic_run, tmp_path, capsys):
    out_path = tmp_path / "seq.e57"
    out_path.write_bytes(b"precious")
    code, _, err = run_cli(["slice", "-t", synthetic_run.trajectory_path, "-c", synthetic_run.cloud_path,
                            "-o", out_path], capsys)
    assert code == 1
    assert err.strip() == f"kinreg: error: {out_path}: exists; use --overwrite to replace it"
    assert out_path.read_bytes() == b"precious"


def test_bad_trajectory_is_one_line_and_no_output(synthetic_run, tmp_path, capsys):
    bad = tmp_path / "bad.txt"
    lines = synthetic_run.trajectory_path.read_text().splitlines()
    lines[10] = lines[10].replace(lines[10].split()[2], "oops", 1)
    bad.write_text("\n".join(lines) + "\n")
    out_path = tmp_path / "seq.e57"
    code, _, err = run_cli(["slice", "-t", bad, "-c", synthetic_run.cloud_path, "-o", out_path], capsys)
    assert code == 1
    assert err.strip() == f"kinreg: error: {bad}: row 11: 'oops' is not a number"
    assert not out_path.exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary left


def test_truncated_cloud_leaves_no_partial_output(synthetic_run, tmp_path, capsys):
    cut = tmp_path / "cut.laz"
    data = synthetic_run.cloud_path.read_bytes()
    cut.write_bytes(data[: len(data) * 2 // 3])
    out_dir = tmp_path / "out"
    code, _, err = run_cli(["slice", "-t", synthetic_run.trajectory_path, "-c", cut, "-o", out_dir / "s.e57"],
                           capsys)
    assert code == 1 and str(cut) in err and len(err.strip().splitlines()) == 1
    assert not any(out_dir.iterdir())


def test_config_defaults_round_trip(capsys, tmp_path):
    code, out, _ = run_cli(["config", "--defaults"], capsys)
    assert code == 0
    parsed = tomllib.loads(out)
    assert parsed["slicing"]["window_s"] == 6.0
    cfg = tmp_path / "k.toml"
    cfg.write_text(out.replace("window_s = 6.0", "window_s = 4.0"))
    code, out, _ = run_cli(["config", "--config", cfg], capsys)
    assert code == 0 and "window_s = 4.0" in out


def test_bad_config_value(capsys, tmp_path):
    cfg = tmp_path / "k.toml"
    cfg.write_text("[slicing]\nwindow_s = -1\n")
    code, _, err = run_cli(["config", "--config", cfg], capsys)
    assert code == 1 and err.strip() == f"kinreg: error: {cfg}: [slicing] window_s: must be positive, got -1.0"
    cfg.write_text("[slicing]\nwindow = 3\n")
    code, _, err = run_cli(["config", "--config", cfg], capsys)
    assert code == 1 and "unknown key(s) window" in err


def test_console_script_has_no_traceback(tmp_path):
    res = subprocess.run([sys.executable, "-m", "kinreg_cli", "info", str(tmp_path / "missing.laz")],
                         capture_output=True, text=True)
    assert res.returncode == 1
    assert res.stderr.strip() == f"kinreg: error: {tmp_path / 'missing.laz'}: file not found"
    assert "Traceback" not in res.stderr
