"""Case files: which grid, which patches are walls, symmetry planes or fixed, how the walls move.

A case file is TOML (layout in ``docs/formats.md``)::

    grid = "naca0012_c_257x65.x"        # relative to the case file
    output = "moved.x"                   # optional, relative to the case file
    walls = ["1:jmin:65-193"]            # BLOCK:FACE[:A1-A2,B1-B2], 1-based, inclusive
    symmetry = []
    fixed = ["1:jmax", "1:imin", "1:imax"]

    [motion]                             # optional
    rotate = 10.0                        # degrees, right-handed about `axis`
    axis = [0.0, 0.0, 1.0]
    about = [0.25, 0.0, 0.0]
    translate = [0.0, 0.05, 0.0]
    twist = 5.0                          # optional: degrees at the span
    bend = 0.15                          # optional: deflection at the span
    span_axis = [0.0, 1.0, 0.0]          # the beam axis (through `about`)
    span = 1.5
    direction = [0.0, 0.0, 1.0]          # bend direction

The grid may be any format :func:`tfi_quat.read` reads.  A CGNS grid brings
its own walls, symmetry planes and fixed faces (its boundary conditions):
a case for one may leave ``walls``, ``symmetry`` and ``fixed`` out, and the
patches it does give override the file's face part by face part
(:class:`tfi_quat.deform.Deformer`).

:func:`load_case` reads and validates one (unknown keys, bad patch strings,
wrong types and a missing grid file are :class:`~tfi_quat.errors.CaseError`
naming the case file and the key); :func:`save_case` writes one.
"""

from __future__ import annotations

import math
import os
import sys
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np

from .errors import CaseError
from .io._atomic import atomic_output, read_text
from .spec import PatchSpec, parse_patch_spec

try:  # Python >= 3.11
    import tomllib as _toml
except ModuleNotFoundError:  # pragma: no cover - Python 3.10
    import tomli as _toml  # type: ignore[no-redef]

__all__ = ["Case", "Motion", "load_case", "save_case", "unit_vector", "DEFORMATIONS"]

#: named wall deformations of :class:`Motion`
DEFORMATIONS = ("bend", "twist")

#: largest case file read (bytes)
CASE_LIMIT = 1 << 20

_PATCH_KEYS = ("walls", "symmetry", "fixed")
_TOP_KEYS = ("grid", "output") + _PATCH_KEYS + ("motion",)


def _vec3(value, what: str) -> tuple[float, float, float]:
    """Three finite numbers from a TOML array (a string such as ``"001"`` or booleans are refused)."""
    if not isinstance(value, (list, tuple)) or len(value) != 3 or any(
            isinstance(c, bool) or not isinstance(c, (int, float)) for c in value):
        raise CaseError(f"{what}: expected 3 numbers [x, y, z], got {_show(value)}")
    try:
        return tuple(_num(c, what) for c in value)  # type: ignore[return-value]
    except CaseError:
        raise CaseError(f"{what}: expected 3 finite numbers, got {_show(value)}") from None


def _show(value) -> str:
    """``repr`` of a value for an error message, shortened."""
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _num(value, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise CaseError(f"{what}: expected a number, got {_show(value)}")
    try:
        v = float(value)
    except OverflowError:       # a TOML integer beyond the float range
        v = math.inf
    if not math.isfinite(v):
        raise CaseError(f"{what}: expected a finite number, got {_show(value)}")
    return v


def unit_vector(v, what: str) -> np.ndarray:
    """``v / |v|`` without overflow or underflow (``[0, 0, 1e200]`` and ``[1e-200, 0, 0]`` included)."""
    a = np.asarray(v, dtype=np.float64)
    scale = np.abs(a).max()
    if not scale > 0.0:
        raise CaseError(f"{what}: must not be the zero vector")
    a = a / scale                       # largest entry +-1: the norm is between 1 and sqrt(3)
    return a / math.sqrt(float(a @ a))


def _rotation_matrix(axis, angle_deg: float) -> np.ndarray:
    a = unit_vector(axis, "axis")
    t = math.radians(angle_deg)
    k = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    return np.eye(3) + math.sin(t) * k + (1.0 - math.cos(t)) * (k @ k)


@dataclass(frozen=True)
class Motion:
    """A prescribed wall motion: a beam-like twist and bend, then a rigid motion.

    The deformation acts along a *beam axis*, the line through ``about``
    along ``span_axis``.  With ``eta = (p - about) . span_axis`` the distance
    of a point's section from ``about`` and ``s = max(eta, 0) / span``:

    1. **twist**: the section turns about the beam axis by
       ``theta(s) = twist * s**2`` degrees;
    2. **bend**: the beam axis is deflected along ``direction`` by
       ``f(s) = bend * s**2`` and every section turns with the slope of the
       bent axis (plane sections stay plane and normal to it: Euler-Bernoulli
       beam kinematics), so a wing's sections keep their shape and the wall
       moves locally like a rigid body;
    3. the rigid rotation (``rotate`` degrees about ``axis`` through
       ``about``) and the translation.

    Beyond ``s = 1`` both go on along their tangent (``twist * (2 s - 1)``,
    ``bend * (2 s - 1)``): the motion stays smooth, so what lies past the
    span (a wing-tip cap) moves with the last section instead of shearing
    against it.  ``s = 0`` for ``eta <= 0``: nothing behind ``about`` deforms.

    Attributes
    ----------
    rotate : float
        Rigid rotation angle, degrees, right-handed about ``axis``.
    axis : (3,) floats
        Rotation axis (non-zero; normalised on use).
    about : (3,) floats
        A point on the rotation axis and on the beam axis.
    translate : (3,) floats
        Rigid translation, applied last.
    bend : float
        Deflection (length) of the beam axis at ``s = 1``.
    twist : float
        Twist angle (degrees) at ``s = 1``, right-handed about ``span_axis``.
    span_axis : (3,) floats
        Direction of the beam axis.
    span : float
        Length over which the deformation grows (> 0).
    direction : (3,) floats
        Bend direction (its component normal to ``span_axis`` is used).
    deformation, amplitude :
        The older single-deformation form: ``deformation = "bend"`` (or
        ``"twist"``) with ``amplitude`` means ``bend = amplitude`` (or
        ``twist = amplitude``); not together with ``bend``/``twist``.
    """

    rotate: float = 0.0
    axis: tuple[float, float, float] = (0.0, 0.0, 1.0)
    about: tuple[float, float, float] = (0.0, 0.0, 0.0)
    translate: tuple[float, float, float] = (0.0, 0.0, 0.0)
    bend: float = 0.0
    twist: float = 0.0
    span_axis: tuple[float, float, float] = (0.0, 1.0, 0.0)
    span: float = 1.0
    direction: tuple[float, float, float] = (0.0, 0.0, 1.0)
    deformation: str | None = None
    amplitude: float | None = None

    def __post_init__(self):
        set_ = object.__setattr__
        for name in ("rotate", "span", "bend", "twist"):
            set_(self, name, _num(getattr(self, name), f"motion.{name}"))
        for name in ("axis", "about", "translate", "span_axis", "direction"):
            set_(self, name, _vec3(getattr(self, name), f"motion.{name}"))
        for name in ("axis", "span_axis", "direction"):
            unit_vector(getattr(self, name), f"motion.{name}")
        if self.deformation is not None or self.amplitude is not None:
            if self.deformation is None:
                raise CaseError("motion.amplitude: give it with motion.deformation "
                                f"({' or '.join(map(repr, DEFORMATIONS))}), or use motion.bend / motion.twist")
            if not isinstance(self.deformation, str) or self.deformation.lower() not in DEFORMATIONS:
                raise CaseError(f"motion.deformation: expected one of {', '.join(DEFORMATIONS)}, "
                                f"got {self.deformation!r}")
            if self.bend != 0.0 or self.twist != 0.0:
                raise CaseError("motion: give either deformation/amplitude or bend/twist, not both")
            amp = _num(0.0 if self.amplitude is None else self.amplitude, "motion.amplitude")
            set_(self, self.deformation.lower(), amp)
            set_(self, "deformation", None)
            set_(self, "amplitude", None)
        if self.span <= 0.0:
            raise CaseError(f"motion.span: must be > 0, got {self.span}")
        if self.span < sys.float_info.min or not math.isfinite(self.bend / self.span):
            raise CaseError(f"motion.span: {self.span!r} is too small (it must be a normal positive number "
                            "and bend/span finite)")
        if self.bend != 0.0:
            sa = unit_vector(self.span_axis, "motion.span_axis")
            d = unit_vector(self.direction, "motion.direction")
            if np.linalg.norm(d - (d @ sa) * sa) < 1e-9:
                raise CaseError("motion.direction: must not be parallel to motion.span_axis")

    # dict-like access, for code that treats the motion as a mapping
    def keys(self) -> list[str]:
        """Field names, in declaration order (the older deformation/amplitude form left out)."""
        return [f.name for f in fields(self) if f.name not in ("deformation", "amplitude")]

    def __getitem__(self, key: str):
        if key not in self.keys():
            raise KeyError(key)
        return getattr(self, key)

    def get(self, key: str, default=None):
        """Field value by name, ``default`` for an unknown name."""
        return getattr(self, key) if key in self.keys() else default

    def to_dict(self) -> dict:
        """The motion as a plain dict (vectors as lists).

        Leaves out the beam keys when there is no bend or twist, and
        ``direction`` unless there is a bend.
        """
        skip = {"deformation", "amplitude"}
        if self.bend == 0.0 and self.twist == 0.0:
            skip |= {"bend", "twist", "span_axis", "span", "direction"}
        elif self.bend == 0.0:
            skip |= {"direction"}
        return {f.name: (list(v) if isinstance(v, tuple) else v)
                for f in fields(self) if f.name not in skip
                for v in (getattr(self, f.name),)}

    @property
    def is_rigid(self) -> bool:
        """True when there is no bend and no twist."""
        return self.bend == 0.0 and self.twist == 0.0

    def describe(self) -> str:
        """One line for logs and the CLI."""
        parts = []
        beam = f"along {tuple(self.span_axis)} from {tuple(self.about)}, span {self.span:g}"
        if self.twist:
            parts.append(f"twisted {self.twist:g} deg")
        if self.bend:
            parts.append(f"bent {self.bend:g} towards {tuple(self.direction)}")
        text = (" and ".join(parts) + f" ({beam}), ") if parts else ""
        return (text + f"rotated {self.rotate:g} deg about axis {tuple(self.axis)} through "
                f"{tuple(self.about)}, translated {tuple(self.translate)}")

    def apply(self, points) -> np.ndarray:
        """Moved positions of ``points``.

        Parameters
        ----------
        points : array_like, shape (..., 3)

        Returns
        -------
        ndarray of float64, shape (..., 3)
            A new array; the input is not modified.
        """
        p = np.array(points, dtype=np.float64)
        if p.shape[-1:] != (3,):
            raise CaseError(f"motion.apply: points must have shape (..., 3), got {p.shape}")
        c = np.asarray(self.about)
        with np.errstate(all="ignore"):     # non-finite results are reported below, not warned about
            if not self.is_rigid:
                sa = unit_vector(self.span_axis, "motion.span_axis")
                eta = (p - c) @ sa
                s = np.maximum(eta, 0.0) / self.span
                inner = s <= 1.0
                grow = np.where(inner, s * s, 2.0 * s - 1.0)          # C1 past the span
                a = c + eta[..., None] * sa                            # section centre on the beam axis
                r = p - a
                if self.twist:
                    r = _rodrigues(r, sa, np.radians(self.twist) * grow)
                if self.bend:
                    d = unit_vector(self.direction, "motion.direction")
                    d = d - (d @ sa) * sa
                    d /= np.linalg.norm(d)
                    slope = self.bend / self.span * np.where(inner, 2.0 * s, 2.0)
                    r = _rodrigues(r, np.cross(sa, d), np.arctan(slope))
                    a = a + (self.bend * grow)[..., None] * d
                p = a + r
            if self.rotate != 0.0:
                p = c + (p - c) @ _rotation_matrix(self.axis, self.rotate).T
            p = p + np.asarray(self.translate)
        bad = ~np.isfinite(p).all(axis=-1)
        if bad.any():
            raise CaseError(f"motion: moves {int(bad.sum())} point(s) to non-finite positions "
                            f"({self.describe()}); check the sizes of translate, bend, twist and span")
        return p


def _rodrigues(r: np.ndarray, axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rotate vectors ``r (..., 3)`` about the unit ``axis`` by per-vector ``angle`` (radians)."""
    cs = np.cos(angle)[..., None]
    sn = np.sin(angle)[..., None]
    return r * cs + np.cross(axis, r) * sn + axis * (r @ axis)[..., None] * (1.0 - cs)


@dataclass
class Case:
    """A deformation case.

    Attributes
    ----------
    grid : Path
        The grid file (absolute after :func:`load_case`).
    walls, symmetry, fixed : list of PatchSpec
        Patches (0-based in the API, 1-based in the file); may be empty for
        a grid that carries its own (CGNS).
    motion : Motion or None
    output : Path or None
        Where to write the result (absolute after :func:`load_case`).
    source : Path or None
        The case file this case was read from.
    """

    grid: Path
    walls: list[PatchSpec] = field(default_factory=list)
    symmetry: list[PatchSpec] = field(default_factory=list)
    fixed: list[PatchSpec] = field(default_factory=list)
    motion: Motion | None = None
    output: Path | None = None
    source: Path | None = None

    def check(self, grid) -> "Case":
        """Check every patch against ``grid``; return a case with explicit ranges.

        Raises
        ------
        CaseError
            A patch names a block or range the grid does not have.
        """
        where = f"{self.source}: " if self.source else ""
        out = {}
        for key in _PATCH_KEYS:
            resolved = []
            for n, p in enumerate(getattr(self, key)):
                try:
                    resolved.append(p.resolve(grid))
                except CaseError as exc:
                    raise CaseError(f"{where}{key}[{n}]: {exc}") from None
            out[key] = resolved
        return Case(self.grid, out["walls"], out["symmetry"], out["fixed"], self.motion,
                    self.output, self.source)


def _patches(data, key: str, where: str) -> list[PatchSpec]:
    value = data.get(key, [])
    if isinstance(value, str) or not isinstance(value, list):
        raise CaseError(f"{where}: key {key!r}: expected a list of patch strings, got {_show(value)}")
    out = []
    for n, text in enumerate(value):
        if not isinstance(text, str):
            raise CaseError(f"{where}: key {key!r}[{n}]: expected a patch string "
                            f"\"BLOCK:FACE[:A1-A2,B1-B2]\", got {_show(text)}")
        try:
            out.append(parse_patch_spec(text))
        except CaseError as exc:
            raise CaseError(f"{where}: key {key!r}[{n}]: {exc}") from None
    return out


def _motion(value, where: str) -> Motion:
    if not isinstance(value, dict):
        raise CaseError(f"{where}: key 'motion': expected a table [motion], got {_show(value)}")
    known = {f.name for f in fields(Motion)}
    for key in value:
        if key not in known:
            raise CaseError(f"{where}: unknown key 'motion.{key}' (known: {', '.join(sorted(known))})")
    try:
        return Motion(**value)
    except CaseError as exc:
        raise CaseError(f"{where}: {exc}") from None


def load_case(path, check_grid: bool = True) -> Case:
    """Read a TOML case file.

    Parameters
    ----------
    path : str or path-like
    check_grid : bool
        Require the grid file to exist.

    Returns
    -------
    Case
        With ``grid`` and ``output`` resolved against the case file's folder.

    Raises
    ------
    FileNotFoundError, IsADirectoryError, PermissionError
        The case file cannot be opened (the path is in the exception).
    CaseError
        Not UTF-8, TOML syntax, unknown keys, wrong types, bad patch strings,
        bad motion values (not finite, a zero or string vector, a span too
        small), missing grid file; the message names the case file and the
        key.
    """
    p = Path(os.fspath(path))
    where = str(p)
    text = read_text(p, CaseError, limit=CASE_LIMIT)
    try:
        data = _toml.loads(text)
    except _toml.TOMLDecodeError as exc:
        raise CaseError(f"{where}: TOML syntax error: {exc}") from None
    except RecursionError:
        raise CaseError(f"{where}: TOML syntax error: arrays or tables nested too deeply") from None
    for key in data:
        if key not in _TOP_KEYS:
            raise CaseError(f"{where}: unknown key {key!r} (known: {', '.join(_TOP_KEYS)})")
    base = p.resolve().parent
    if "grid" not in data:
        raise CaseError(f"{where}: key 'grid' is missing (the grid file, relative to the case file)")
    paths = {}
    for key in ("grid", "output"):
        if key in data:
            if not isinstance(data[key], str) or not data[key].strip():
                raise CaseError(f"{where}: key {key!r}: expected a file name, got {_show(data[key])}")
            paths[key] = Path(os.path.normpath(base / data[key]))
    if check_grid and not paths["grid"].is_file():
        what = "is a directory" if paths["grid"].is_dir() else "does not exist"
        raise CaseError(f"{where}: key 'grid': grid file {paths['grid']} {what}")
    motion = _motion(data["motion"], where) if "motion" in data else None
    return Case(grid=paths["grid"], walls=_patches(data, "walls", where),
                symmetry=_patches(data, "symmetry", where), fixed=_patches(data, "fixed", where),
                motion=motion, output=paths.get("output"), source=p)


# ---------------------------------------------------------------- writing
def _toml_str(s: str) -> str:
    out = ['"']
    for ch in s:
        if ch in '"\\':
            out.append("\\" + ch)
        elif ord(ch) < 0x20 or ord(ch) == 0x7F:
            out.append(f"\\u{ord(ch):04X}")
        else:
            out.append(ch)
    out.append('"')
    return "".join(out)


def _toml_value(v) -> str:
    if isinstance(v, str):
        return _toml_str(v)
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(float(v))
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise CaseError(f"cannot write {v!r} to a case file")


def _rel(target: Path, base: Path) -> str:
    target = Path(os.path.abspath(target))
    try:
        return Path(os.path.relpath(target, base)).as_posix()
    except ValueError:  # another drive on Windows
        return target.as_posix()


def save_case(path, case: Case) -> None:
    """Write ``case`` as a TOML case file.

    ``grid`` and ``output`` are written relative to the case file's folder
    (absolute when that is impossible); patches in their 1-based text form.

    Parameters
    ----------
    path : str or path-like
    case : Case
    """
    p = Path(os.fspath(path))
    base = Path(os.path.abspath(p)).parent
    lines = ["# tfi_quat case file (docs/formats.md)",
             f"grid = {_toml_str(_rel(Path(case.grid), base))}"]
    if case.output is not None:
        lines.append(f"output = {_toml_str(_rel(Path(case.output), base))}")
    for key in _PATCH_KEYS:
        specs = getattr(case, key)
        if not all(isinstance(s, PatchSpec) for s in specs):
            raise CaseError(f"{p}: {key}: expected PatchSpec items")
        lines.append(f"{key} = {_toml_value([str(s) for s in specs])}")
    if case.motion is not None:
        lines += ["", "[motion]"]
        for key, value in case.motion.to_dict().items():
            lines.append(f"{key} = {_toml_value(value)}")
    text = "\n".join(lines) + "\n"
    with atomic_output(p, "wb") as fh:
        fh.write(text.encode("utf-8"))
