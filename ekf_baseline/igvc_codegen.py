"""Symbolic derivation (sympy) of seed 000's 11-state motion models and generation of their code.

The seed derives the Jacobian F of its motion model with sympy and substitutes numbers into it at
every step. Substituting into sympy expressions costs milliseconds per step, so here the model and
its Jacobian are derived ONCE and printed as plain-``math`` Python into
``ekf_baseline/igvc_jacobians.py`` (committed). ``tests/test_igvc_jacobians.py`` re-derives the
code and fails when the committed file is out of date. Regenerate with::

    python3 -m ddfuse.ekf_baseline.igvc_codegen

State (index: symbol, unit), corrected as listed in docs/errata.md "Seed 000":

    0 lat      geodetic latitude, rad                 (seed: phi)
    1 lon      longitude, rad                         (seed: lambda)
    2 theta    global heading: bearing, rad, CLOCKWISE from true north (what eqs. 4-5 need)
    3 x        local ENU east, m                      (seed: x north -- converted, see below)
    4 y        local ENU north, m                     (seed: y east)
    5 psi      local heading: yaw, rad, counter-clockwise from local x (east)
    6 v        forward speed, m/s
    7 psi_dot  yaw rate, rad/s, counter-clockwise positive
    8 v_l      left wheel rim speed, m/s (a linear speed: no wheel radius multiplies it)
    9 v_r      right wheel rim speed, m/s
   10 a        forward acceleration, m/s^2

The seed states x north / y east with a heading that is "left positive"; with eqs. 6-7
(x' = v cos psi, y' = v sin psi) that combination is a left-handed frame in which psi would
increase to the right. The filter therefore runs in the project's right-handed local ENU frame
(x east, y north, psi CCW from east) throughout; theta stays a compass bearing (clockwise from
north) because that is what the great-circle formulas take, so theta = pi/2 - psi + const and
theta' = -psi_dot.

Motion models (``dt`` s, track width ``track`` m, sphere radius ``radius`` m), both built from the
primary kinematic states v, psi_dot, a; the wheel speeds are slaved to them each step
(v_l = v - psi_dot track/2, v_r = v + psi_dot track/2) so the redundant states of the seed's
11-vector never contradict each other:

* ``euler`` -- the seed's eqs. 9-12 and 14, corrected: first-order position, heading and speed
  steps, lat/lon by the great-circle forward formulas (eqs. 4-5) with the signed distance v dt
  along the bearing theta.
* ``icc`` -- the seed's appendix (eqs. 28-33), the exact circular arc about the instantaneous
  centre of curvature, written without the turn radius R = v/psi_dot so that it is smooth through
  psi_dot = 0: with alpha = psi_dot dt, S(alpha) = sin(alpha)/alpha and
  C(alpha) = (1 - cos alpha)/alpha,
      x' = x + v dt (cos(psi) S - sin(psi) C),   y' = y + v dt (sin(psi) S + cos(psi) C),
  which equals eqs. 31-32 for psi_dot != 0 and tends to the straight line as psi_dot -> 0. The
  lat/lon step uses the chord of the same arc: length v dt S(alpha/2), bearing theta - alpha/2.
  S, C and their derivatives are evaluated by ``factors.kinematics.twist_coeffs`` (Taylor series
  below |alpha| = 0.1, closed form above), so neither the values nor F lose digits near 0.
"""

from __future__ import annotations

import sys
import textwrap
from pathlib import Path

import sympy as sp

STATE_NAMES = (
    "lat", "lon", "theta", "x", "y", "psi", "v", "psi_dot", "v_l", "v_r", "a",
)
N = len(STATE_NAMES)
TARGET = Path(__file__).with_name("igvc_jacobians.py")
LINE = 100  # ruff line length of the project


class Sinc(sp.Function):
    """S(a) = sin(a)/a, continued by S(0) = 1; evaluated numerically by twist_coeffs."""

    def fdiff(self, argindex=1):
        return DSinc(self.args[0])


class Cosc(sp.Function):
    """C(a) = (1 - cos a)/a, continued by C(0) = 0; evaluated numerically by twist_coeffs."""

    def fdiff(self, argindex=1):
        return DCosc(self.args[0])


class DSinc(sp.Function):
    """S'(a); only its value is needed (F holds first derivatives)."""


class DCosc(sp.Function):
    """C'(a); only its value is needed."""


def _symbols():
    s = sp.symbols(STATE_NAMES, real=True)
    dt, track, radius = sp.symbols("dt track radius", positive=True)
    return s, dt, track, radius


def _great_circle(lat, lon, bearing, dist, radius):
    """Seed eqs. 4-5 with the distance and the radius both in metres."""
    delta = dist / radius
    lat1 = sp.asin(sp.sin(lat) * sp.cos(delta) + sp.cos(lat) * sp.sin(delta) * sp.cos(bearing))
    lon1 = lon + sp.atan2(
        sp.sin(bearing) * sp.sin(delta) * sp.cos(lat),
        sp.cos(delta) - sp.sin(lat) * sp.sin(lat1),
    )
    return lat1, lon1


def motion_model(kind: str):
    """f(s, dt) of the 11-state model as a sympy Matrix (11, 1), with the symbols used.

    ``kind`` is 'euler' or 'icc'. Returns (f, state_symbols, dt, track, radius)."""
    s, dt, track, radius = _symbols()
    lat, lon, theta, x, y, psi, v, psi_dot, _v_l, _v_r, a = s
    turn = psi_dot * dt
    if kind == "euler":
        # Seed eqs. 6-7 with (r/2)(v_l + v_r) = v; eq. 3's distance signed: v dt.
        x1 = x + v * sp.cos(psi) * dt
        y1 = y + v * sp.sin(psi) * dt
        lat1, lon1 = _great_circle(lat, lon, theta, v * dt, radius)
    elif kind == "icc":
        S, C = Sinc(turn), Cosc(turn)
        x1 = x + v * dt * (sp.cos(psi) * S - sp.sin(psi) * C)
        y1 = y + v * dt * (sp.sin(psi) * S + sp.cos(psi) * C)
        # chord of the arc: length v dt S(turn/2), direction halfway through the turn; the
        # bearing is clockwise, so a CCW turn decreases it.
        lat1, lon1 = _great_circle(lat, lon, theta - turn / 2, v * dt * Sinc(turn / 2), radius)
    else:
        raise ValueError(f"unknown motion model {kind!r} (use 'euler' or 'icc')")
    v1 = v + a * dt
    f = sp.Matrix([
        lat1,
        lon1,
        theta - turn,  # bearing is clockwise; psi_dot is counter-clockwise
        x1,
        y1,
        psi + turn,
        v1,
        psi_dot,
        v1 - psi_dot * track / 2,  # wheel speeds slaved to (v, psi_dot) at the end of the step
        v1 + psi_dot * track / 2,
        a,
    ])
    return f, s, dt, track, radius


def jacobian(kind: str):
    """(f, F) of motion model ``kind``: F = df/ds, an (11, 11) sympy Matrix."""
    f, s, *_ = motion_model(kind)
    return f, f.jacobian(sp.Matrix(s))


# ----------------------------------------------------------------------------- code printing
def _wrap(prefix: str, expr: str, indent: str, suffix: str = "") -> list[str]:
    """Lines for ``prefix + expr + suffix`` within LINE columns; long ones are parenthesised and
    broken at spaces (sympy's printer puts spaces only around binary +/- and after commas, all
    legal break points inside parentheses)."""
    one = f"{indent}{prefix}{expr}{suffix}"
    if len(one) <= LINE:
        return [one]
    inner = indent + "    "
    body = textwrap.wrap(expr, width=LINE - len(inner), break_long_words=False,
                         break_on_hyphens=False)
    if any(len(inner + b) > LINE for b in body):
        raise ValueError(f"cannot wrap generated expression to {LINE} columns: {expr[:60]}...")
    return [f"{indent}{prefix}(", *[inner + b for b in body], f"{indent}){suffix}"]


def _print(e) -> str:
    if e == 0:
        return "0.0"
    if e == 1:
        return "1.0"
    if e.is_Number:
        return repr(float(e))
    return sp.pycode(e, fully_qualified_modules=True)


def _function_code(kind: str) -> str:
    f, F = jacobian(kind)
    s, dt, track, radius = _symbols()
    turn = s[7] * dt
    subs = {}
    pre = []
    if kind == "icc":
        s1, c1, ds1, dc1, s2, ds2 = sp.symbols("s1 c1 ds1 dc1 s2 ds2", real=True)
        subs = {
            Sinc(turn): s1, Cosc(turn): c1, DSinc(turn): ds1, DCosc(turn): dc1,
            Sinc(turn / 2): s2, DSinc(turn / 2): ds2,
        }
        pre = [
            "    # S, C of the turn and of the half turn (chord length), series near 0",
            "    s1, c1, ds1, dc1 = twist_coeffs(psi_dot * dt)",
            "    s2, _, ds2, _ = twist_coeffs(0.5 * psi_dot * dt)",
        ]
    fx = [sp.sympify(e).xreplace(subs) for e in f]
    Fx = [sp.sympify(e).xreplace(subs) for e in F]
    leftover = [e for e in fx + Fx if e.atoms(Sinc, Cosc, DSinc, DCosc)]
    if leftover:
        raise RuntimeError(f"unsubstituted S/C functions in {kind} model: {leftover[0]}")
    reps, red = sp.cse(fx + Fx, symbols=sp.numbered_symbols("t"), order="canonical")
    fr, Fr = red[:N], red[N:]
    used = set()
    for e in [r[1] for r in reps] + red:
        used |= {str(a) for a in e.free_symbols}
    unpack = ", ".join(n if n in used else "_" for n in STATE_NAMES)
    model = {"euler": "First-order (seed eqs. 4-14, corrected)",
             "icc": "Exact ICC arc (seed appendix A, eqs. 28-33, corrected)"}[kind]
    # F's sparsity: structurally zero, constant one, or computed each step (row-major flat index)
    ones = [i * N + j for i in range(N) for j in range(N) if F[i, j] == 1]
    variable = [i * N + j for i in range(N) for j in range(N) if F[i, j] not in (0, 1)]
    up = kind.upper()
    lines = [
        f"{up}_F_ONES = {tuple(ones)!r}",
        f"{up}_F_VARIABLE = {tuple(variable)!r}",
        "",
        "",
        f"def {kind}_step_sparse(s, dt, track, radius):",
        '    """Motion step f and the nonzero entries of its Jacobian F = df/ds.',
        "",
        f"    {model} model.",
        "    ``s`` is the 11-state (see STATE_NAMES; rad, m, m/s, rad/s, m/s^2), ``dt`` the step",
        "    (s), ``track`` the wheel track width (m), ``radius`` the Earth sphere's radius (m).",
        "    Returns (f, fv): the predicted state as an 11-tuple (angles not wrapped) and the",
        f"    entries of F = df/ds at the row-major flat indices {up}_F_VARIABLE; the entries",
        f'    at {up}_F_ONES are 1, all others 0."""',
        f"    {unpack} = s",
        *pre,
    ]
    for sym, e in reps:
        lines += _wrap(f"{sym} = ", _print(e), "    ")
    lines.append("    f = (")
    for e in fr:
        lines += _wrap("", _print(e), "        ", ",")
    lines.append("    )")
    lines.append("    fv = (")
    for k in variable:
        lines += _wrap("", _print(Fr[k]), "        ", ",")
    lines.append("    )")
    lines.append("    return f, fv")
    lines += [
        "",
        "",
        f"def {kind}_step(s, dt, track, radius):",
        f'    """{kind}_step_sparse with F dense: returns (f, F), F as 11 rows of 11 floats."""',
        f"    f, fv = {kind}_step_sparse(s, dt, track, radius)",
        f"    return f, _dense(fv, {up}_F_VARIABLE, {up}_F_ONES)",
    ]
    return "\n".join(lines) + "\n"


def generate() -> str:
    """The full text of ``igvc_jacobians.py``."""
    head = f'''"""GENERATED by ekf_baseline/igvc_codegen.py -- do not edit; regenerate with
``python3 -m ekf_baseline.igvc_codegen``. tests/test_igvc_jacobians.py checks it is up to date.

Seed 000's 11-state motion models f and their sympy-derived Jacobians F = df/ds in plain math.
State order and units: STATE_NAMES; frames and corrections: ekf_baseline/igvc_codegen.py.
"""

import math

from ddfuse.factors.kinematics import twist_coeffs

# sympy version that printed this file (another version may print equivalent code differently)
SYMPY_VERSION = {sp.__version__!r}

STATE_NAMES = {STATE_NAMES!r}


def _dense(fv, variable, ones):
    """The 11 x 11 Jacobian as rows of floats from its variable entries and its ones."""
    flat = [0.0] * {N * N}
    for k in ones:
        flat[k] = 1.0
    for k, v in zip(variable, fv, strict=True):
        flat[k] = v
    return tuple(tuple(flat[i:i + {N}]) for i in range(0, {N * N}, {N}))


'''
    body = "\n\n".join(_function_code(k) for k in ("euler", "icc"))
    text = head + body
    # the euler model never calls twist_coeffs; import only what is used (ruff F401)
    if "twist_coeffs(" not in body:
        text = text.replace("from ddfuse.factors.kinematics import twist_coeffs\n", "")
    return text


def main(argv: list[str] | None = None) -> int:
    TARGET.write_text(generate())
    print(f"wrote {TARGET}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
