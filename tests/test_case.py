"""Case files: TOML layout, validation messages, round trips, motion."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tfi_quat import CaseError, Grid
from tfi_quat.case import Case, Motion, load_case, save_case
from tfi_quat.spec import PatchSpec, parse_patch_spec

from conftest import annulus

EXAMPLE = """\
grid = "naca0012_c_257x65.x"
walls = ["1:jmin:65-193"]
fixed = ["1:jmax", "1:imin", "1:imax"]
symmetry = []
[motion]
rotate = 10.0
axis = [0.0, 0.0, 1.0]
about = [0.25, 0.0, 0.0]
translate = [0.0, 0.05, 0.0]
"""


@pytest.fixture
def folder(tmp_path):
    (tmp_path / "naca0012_c_257x65.x").write_bytes(b"\0")
    return tmp_path


def write(folder: Path, text: str, name="case.toml") -> Path:
    p = folder / name
    p.write_text(text, encoding="utf-8")
    return p


def test_load_the_documented_example(folder):
    case = load_case(write(folder, EXAMPLE))
    assert case.grid == (folder / "naca0012_c_257x65.x").resolve()
    assert case.walls == [PatchSpec(0, "jmin", ((64, 192), (0, 0)))]
    assert case.fixed == [PatchSpec(0, f) for f in ("jmax", "imin", "imax")]
    assert case.symmetry == [] and case.output is None
    m = case.motion
    assert m.rotate == 10.0 and m.axis == (0.0, 0.0, 1.0) and m.about == (0.25, 0.0, 0.0)
    assert m["translate"] == (0.0, 0.05, 0.0) and m.is_rigid and m.get("nothing", 7) == 7


def test_grid_is_relative_to_the_case_file(folder, monkeypatch):
    sub = folder / "cases"
    sub.mkdir()
    p = write(sub, 'grid = "../naca0012_c_257x65.x"\noutput = "out/moved.x"\n')
    monkeypatch.chdir(sub.parent.parent)
    case = load_case(p)
    assert case.grid == (folder / "naca0012_c_257x65.x").resolve()
    assert case.output == sub.resolve() / "out" / "moved.x"
    assert case.walls == [] and case.motion is None


def test_round_trip(folder):
    motion = Motion(rotate=-3.5, axis=(0, 1, 0), about=(0.25, 0, 0), translate=(0, 0, 0.1),
                    deformation="bend", amplitude=0.2, span_axis=(0, 1, 0), span=1.5,
                    direction=(0, 0, 1))
    case = Case(grid=folder / "naca0012_c_257x65.x",
                walls=[parse_patch_spec("1:jmin:17-49,1-9"), parse_patch_spec("2:jmin")],
                symmetry=[parse_patch_spec("1:kmin")], fixed=[parse_patch_spec("3:kmax")],
                motion=motion, output=folder / "result" / "moved grid \"1\".x")
    p = folder / "deep" / "c.toml"
    p.parent.mkdir()
    save_case(p, case)
    text = p.read_text()
    assert 'grid = "../naca0012_c_257x65.x"' in text and '"1:jmin:17-49,1-9"' in text
    back = load_case(p)
    assert back.grid == case.grid.resolve() and back.output == case.output.resolve()
    assert (back.walls, back.symmetry, back.fixed, back.motion) == \
        (case.walls, case.symmetry, case.fixed, case.motion)
    save_case(p, back)
    assert p.read_text() == text


def test_rigid_motion_without_deformation_keys(folder):
    case = Case(grid=folder / "naca0012_c_257x65.x", motion=Motion(rotate=1.0))
    p = folder / "r.toml"
    save_case(p, case)
    text = p.read_text()
    assert "amplitude" not in text and "direction" not in text
    assert load_case(p).motion == Motion(rotate=1.0)


@pytest.mark.parametrize("text,match", [
    ('grid = "naca0012_c_257x65.x"\nwall = ["1:jmin"]\n', "unknown key 'wall'"),
    ('grid = "naca0012_c_257x65.x"\nwalls = ["1:jmin:5-2"]\n', r"'walls'\[0\].*5-2"),
    ('grid = "naca0012_c_257x65.x"\nfixed = ["1:jmax", "1:top"]\n', r"'fixed'\[1\].*top"),
    ('grid = "naca0012_c_257x65.x"\nwalls = "1:jmin"\n', "'walls': expected a list"),
    ('grid = "naca0012_c_257x65.x"\nsymmetry = [1]\n', r"'symmetry'\[0\]: expected a patch string"),
    ('grid = "missing.x"\n', "key 'grid': grid file .*missing.x does not exist"),
    ('walls = []\n', "key 'grid' is missing"),
    ('grid = 3\n', "key 'grid': expected a file name"),
    ('grid = "naca0012_c_257x65.x"\n[motion]\nspin = 3\n', "unknown key 'motion.spin'"),
    ('grid = "naca0012_c_257x65.x"\n[motion]\naxis = [0, 0]\n', "motion.axis"),
    ('grid = "naca0012_c_257x65.x"\n[motion]\naxis = [0, 0, 0]\n', "motion.axis: must not be the zero"),
    ('grid = "naca0012_c_257x65.x"\n[motion]\nrotate = "ten"\n', "motion.rotate"),
    ('grid = "naca0012_c_257x65.x"\n[motion]\ndeformation = "wobble"\n', "motion.deformation"),
    ('grid = "naca0012_c_257x65.x"\n[motion]\ndeformation = "bend"\nspan = 0.0\n', "motion.span"),
    ('grid = "naca0012_c_257x65.x"\nmotion = 3\n', "key 'motion': expected a table"),
    ('grid = "naca0012_c_257x65.x"\nwalls = [\n', "TOML syntax error"),
])
def test_bad_case_files_name_the_file_and_key(folder, text, match):
    p = write(folder, text, "bad.toml")
    with pytest.raises(CaseError, match=match) as info:
        load_case(p)
    assert str(p) in str(info.value)


def test_missing_case_file_and_unchecked_grid(folder):
    with pytest.raises(FileNotFoundError, match="nothere.toml"):
        load_case(folder / "nothere.toml")
    with pytest.raises(IsADirectoryError, match=str(folder)):
        load_case(folder)
    p = write(folder, 'grid = "later.x"\n')
    assert load_case(p, check_grid=False).grid.name == "later.x"


def test_check_against_a_grid(folder):
    g = Grid([annulus(9, 5)])
    case = load_case(write(folder, 'grid = "naca0012_c_257x65.x"\nwalls = ["1:jmin:2-8"]\n'
                                    'fixed = ["1:jmax"]\n'))
    resolved = case.check(g)
    assert resolved.fixed == [PatchSpec(0, "jmax", ((0, 8), (0, 0)))]
    bad = load_case(write(folder, 'grid = "naca0012_c_257x65.x"\nwalls = ["1:jmin:2-10"]\n', "b.toml"))
    with pytest.raises(CaseError, match=r"b.toml: walls\[0\].*exceeds"):
        bad.check(g)
    two = load_case(write(folder, 'grid = "naca0012_c_257x65.x"\nsymmetry = ["2:imin"]\n', "t.toml"))
    with pytest.raises(CaseError, match=r"symmetry\[0\].*1 block"):
        two.check(g)


def test_motion_apply_rigid_and_named():
    rng = np.random.default_rng(3)
    p = rng.normal(size=(20, 3))
    m = Motion(rotate=30.0, axis=(1, 1, 0), about=(0.5, -1.0, 2.0), translate=(0.1, 0.2, 0.3))
    q = m.apply(p)
    # rigid: distances kept, the axis point moves by the translation only
    d0 = np.linalg.norm(p[:, None] - p[None], axis=-1)
    d1 = np.linalg.norm(q[:, None] - q[None], axis=-1)
    assert np.allclose(d0, d1, atol=1e-12)
    assert np.allclose(m.apply([[0.5, -1.0, 2.0]]), [[0.6, -0.8, 2.3]])
    a = np.array([1.0, 1.0, 0.0]) / np.sqrt(2)
    assert np.allclose(m.apply(a * 3 + [0.5, -1.0, 2.0]) - m.translate, a * 3 + [0.5, -1.0, 2.0])
    # quarter turn about z
    q = Motion(rotate=90.0).apply([[1.0, 0.0, 0.0]])
    assert np.allclose(q, [[0.0, 1.0, 0.0]])
    # bend: zero at the root, amplitude at the span end, on along the tangent
    # beyond (slope 2 * 0.3 / 2 = 0.3 per unit span: continuous rotation)
    b = Motion(deformation="bend", amplitude=0.3, span=2.0, span_axis=(0, 1, 0), direction=(0, 0, 1))
    y = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 2.0, 0.0], [0, 5.0, 0]])
    assert np.allclose(b.apply(y)[:, 2], [0.0, 0.0, 0.075, 0.3, 0.3 + 3 * 0.3])
    eps = 1e-6
    slope = (b.apply([[0, 2.0 + eps, 0]]) - b.apply([[0, 2.0 - eps, 0]]))[0, 2] / (2 * eps)
    assert slope == pytest.approx(0.3, rel=1e-6)
    # twist: rotation about the span axis growing like s^2; points on the axis stay
    t = Motion(deformation="twist", amplitude=10.0, span=1.0, span_axis=(0, 1, 0))
    moved = t.apply([[1.0, 1.0, 0.0], [0.0, 0.5, 0.0]])
    assert np.allclose(moved[1], [0.0, 0.5, 0.0])
    ang = np.degrees(np.arctan2(-moved[0, 2], moved[0, 0]))
    assert ang == pytest.approx(-10.0) or ang == pytest.approx(10.0)
    assert np.linalg.norm(moved[0, [0, 2]]) == pytest.approx(1.0)
    src = p.copy()
    m.apply(p)
    assert np.array_equal(p, src)
    with pytest.raises(CaseError, match="shape"):
        m.apply(np.zeros((3, 2)))


def test_beam_motion_keeps_sections_rigid_and_normal_to_the_bent_axis():
    """bend + twist: each section (points of one span station) moves rigidly, turned by the
    twist about the beam axis and by the slope of the bent axis; smooth past the span."""
    m = Motion(bend=0.3, twist=8.0, about=(0.25, 0.0, 0.0), span_axis=(0, 1, 0), span=1.5,
               direction=(0, 0, 1))
    rng = np.random.default_rng(4)
    for eta in (0.0, 0.4, 1.5, 1.9):
        sec = np.c_[rng.uniform(-0.5, 1.5, 30), np.full(30, eta), rng.uniform(-0.1, 0.1, 30)]
        out = m.apply(sec)
        d0 = np.linalg.norm(sec[:, None] - sec[None], axis=-1)
        d1 = np.linalg.norm(out[:, None] - out[None], axis=-1)
        np.testing.assert_allclose(d1, d0, atol=1e-12)            # rigid section
        s = min(eta / 1.5, 1.0)
        grow = s * s if eta <= 1.5 else 2 * eta / 1.5 - 1
        axis_pt = m.apply([[0.25, eta, 0.0]])[0]
        np.testing.assert_allclose(axis_pt, [0.25, eta, 0.3 * grow], atol=1e-14)
        # the section's normal is the tangent of the bent axis
        _, _, vt = np.linalg.svd(out - out.mean(0))
        slope = 0.3 / 1.5 * (2 * s if eta <= 1.5 else 2.0)
        tangent = np.array([0.0, 1.0, slope]) / np.hypot(1.0, slope)
        assert abs(abs(vt[-1] @ tangent) - 1.0) < 1e-12
    # C1 through the span: value and slope of the axis, and the twist, continuous
    eps = 1e-6
    a, b = m.apply([[0.25, 1.5 - eps, 0.0], [0.25, 1.5 + eps, 0.0]])
    assert np.linalg.norm(b - a) < 3 * eps
    lo, hi = m.apply([[1.25, 1.5 - eps, 0.0], [1.25, 1.5 + eps, 0.0]])
    assert np.linalg.norm(hi - lo) < 10 * eps
    # behind `about` nothing deforms
    back = np.array([[1.0, -0.5, 0.02]])
    assert np.array_equal(m.apply(back), back)


def test_older_deformation_form_and_its_errors():
    assert Motion(deformation="bend", amplitude=0.2) == Motion(bend=0.2)
    assert Motion(deformation="Twist", amplitude=3.0) == Motion(twist=3.0)
    with pytest.raises(CaseError, match="not both"):
        Motion(deformation="bend", amplitude=0.2, twist=1.0)
    with pytest.raises(CaseError, match="amplitude"):
        Motion(amplitude=0.2)
    with pytest.raises(CaseError, match="parallel"):
        Motion(bend=0.1, direction=(0, 2, 0))
    m = Motion(bend=0.1, twist=2.0, span=1.5)
    assert "twisted 2 deg" in m.describe() and "bent 0.1" in m.describe()
    assert set(m.to_dict()) >= {"bend", "twist", "span", "direction"}
    assert "direction" not in Motion(twist=2.0).to_dict()
