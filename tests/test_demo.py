"""The demo (the memo's figure 4 experiment) and the near-wall orthogonality measure."""

from __future__ import annotations

import json

import numpy as np
import pytest

import tfi_quat
from tfi_quat import Block, CaseError, Grid
from tfi_quat.cli import main
from tfi_quat.demo import DemoMotion, default_grid_path, run_demo
from tfi_quat.quality import orthogonality_change, wall_orthogonality


def _polar(nr=9, nt=33, r0=1.0, r1=3.0, shear=0.0):
    """2-D annulus grid: i round (open arc), j radial; ``shear`` tilts the radial lines by
    a constant angle (radians) in the tangential direction."""
    t = np.linspace(0.0, 1.5 * np.pi, nt)[:, None]
    r = np.linspace(r0, r1, nr)[None, :]
    th = t + np.tan(shear) * (r - r0) / r
    xyz = np.zeros((nt, nr, 1, 3), order="F")
    xyz[:, :, 0, 0] = r * np.cos(th)
    xyz[:, :, 0, 1] = r * np.sin(th)
    return Grid([Block(xyz)], ndim=2)


def test_wall_orthogonality_zero_on_a_polar_grid_and_on_either_face():
    g = _polar()
    a = wall_orthogonality(g, ["1:jmin"], layers=5)[0]
    assert a.shape == (33, 1, 5)
    assert np.nanmax(a[1:-1]) < 1e-6          # central differences: exact on a circle
    assert np.nanmax(a) < 0.51 * 270.0 / 32   # one-sided at the patch ends: half a step
    b = wall_orthogonality(g, ["1:jmax:3-20"], layers=3)[0]     # max face, sub-range
    assert b.shape == (18, 1, 3) and np.nanmax(b[1:-1]) < 1e-6


def test_wall_orthogonality_sees_a_tilted_line():
    g = _polar()
    x = g[0].xyz.copy(order="F")
    # tilt the first layer's lines by a known angle in the tangential direction
    ang = np.radians(12.0)
    w = x[:, 0, 0, :2]
    n = w / np.linalg.norm(w, axis=1, keepdims=True)
    t = np.stack([-n[:, 1], n[:, 0]], axis=1)
    h = np.linalg.norm(x[:, 1, 0, :2] - w, axis=1, keepdims=True)
    x[:, 1, 0, :2] = w + h * (np.cos(ang) * n + np.sin(ang) * t)
    g2 = Grid([Block(x)], ndim=2)
    a = wall_orthogonality(g2, ["1:jmin"], layers=1)[0][1:-1, 0, 0]
    np.testing.assert_allclose(a, 12.0, atol=1e-6)
    ch = orthogonality_change(g2, g, ["1:jmin"], layers=5)
    assert ch["max"] == pytest.approx(12.0, abs=1e-6)
    assert orthogonality_change(g, g, ["1:jmin"])["max"] == 0.0


def test_wall_orthogonality_3d_patch():
    # an extruded polar grid: k along z, the wall is jmin; lines orthogonal
    g2 = _polar()
    x = np.repeat(g2[0].xyz, 4, axis=2)
    x[..., 2] = np.linspace(0.0, 1.0, 4)[None, None, :]
    g = Grid([Block(np.asfortranarray(x))], ndim=3)
    a = wall_orthogonality(g, ["1:jmin"], layers=4)[0]
    assert a.shape == (33, 4, 4) and np.nanmax(a[1:-1]) < 1e-6 and np.nanmax(a) < 0.51 * 270.0 / 32
    with pytest.raises(ValueError, match="layers"):
        wall_orthogonality(g, ["1:jmin"], layers=0)


def test_demo_writes_grids_figure_and_table(tmp_path):
    res = run_demo(tmp_path, figure=True, repeats=1)
    q, t = res.rows["quaternion TFI"], res.rows["plain TFI"]
    # the memo's point: quaternions keep the near-wall lines, plain TFI shears them
    assert q["ortho_mean"] < 0.05 and t["ortho_mean"] > 10.0
    assert q["negative"] == 0 and q["min_ratio"] > t["min_ratio"]
    m = res.rows["quaternion TFI, memo's update"]
    assert m["negative"] == 0 and m["ortho_mean"] < 0.05
    for name in ("naca0012_tfi.x", "naca0012_samareh.x", "naca0012_quaternion.x", "demo.md", "demo.json",
                 "demo.png"):
        assert (tmp_path / name).exists(), name
    assert (tmp_path / "demo.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    data = json.loads((tmp_path / "demo.json").read_text())
    assert set(data["methods"]) == {"plain TFI", "quaternion TFI, memo's update", "quaternion TFI"}
    # the written grid is the deformed one, and its wall is where the motion put it
    g = tfi_quat.read(tmp_path / "naca0012_quaternion.x")
    ref = tfi_quat.read(default_grid_path())
    w = ref[0].xyz[64:193, 0, 0]
    np.testing.assert_allclose(g[0].xyz[64:193, 0, 0], DemoMotion()(w), atol=1e-12)
    with pytest.raises(CaseError, match="exists"):
        run_demo(tmp_path, figure=False)


def test_demo_cli(tmp_path, capsys):
    assert main(["demo", "-o", str(tmp_path), "--no-figure", "--pitch", "15"]) == 0
    out = capsys.readouterr().out
    assert "pitched 15 deg" in out and "quaternion TFI" in out
    assert main(["demo", "-o", str(tmp_path), "--no-figure"]) == 2
    assert "exists" in capsys.readouterr().err
