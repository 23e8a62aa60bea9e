"""Independent continuation reference for the quasi-steady aerofoil flutter model: AUTO-07p.

The model (paper appendix A.2), states ``y = (h, alpha, h', alpha')``, parameter ``V`` (m/s)::

    M x'' + B(V) x' + S(V) x + (0, k_alpha2 alpha^2 + k_alpha3 alpha^3) = 0,   x = (h, alpha)

    M = [[m_T + rho pi b^2,               m_w x_alpha b - rho pi b^3 a],
         [m_w x_alpha b - rho pi b^3 a,   I_alpha + rho pi b^4 (1/8 + a^2)]]
    B = [[c_h + 2 pi rho b V,             2 pi rho b^2 V (1 - a)],
         [-2 pi rho b^2 V (a + 1/2),      c_alpha - 2 a rho pi b^3 V (1/2 - a)]]
    S = [[k_h,                            2 pi rho b V^2],
         [0,                              k_alpha - 2 pi rho b^2 V^2 (1/2 + a)]]

:func:`auto_flutter_reference` writes the model as an AUTO-07p equations file (Fortran
``FUNC``/``STPNT`` with analytic Jacobians, the parameter values baked in as double
precision constants) plus constants files into a scratch directory, compiles it against
the AUTO-07p library, and runs the executable non-interactively (constants on stdin, the
classic ``@r`` protocol) twice:

1. the trivial equilibrium ``y = 0`` continued in ``V`` over ``v_range`` -> Hopf points (HB);
2. the periodic family from the first HB (``IPS=2``, ``ICP=[1, 11]``) until the first fold of
   limit cycles (LP) or the edge of ``v_range``; this run is done at two mesh sizes
   (``NTST`` and ``2 NTST``, ``NCOL=4``) and the difference is reported as a convergence check.

The Fortran model is a separate transcription from :func:`eigen_hopf` (numpy) and from
``ude_fit``; nothing here imports ``ude_fit``.

Install (Debian 12, root): ``apt-get install -y auto-07p gfortran`` -- the Debian package
ships AUTO-07p 0.9.2 as prebuilt object files plus the Python CLUI but does *not* depend on
a Fortran compiler, which is needed to build every equations file.  ``.ci/auto07p_install.sh``
does this.  A source build can be used instead by pointing ``AUTO_DIR`` at it (must hold
``lib/*.o``); ``FC`` overrides the compiler.
"""

from __future__ import annotations

import functools
import glob
import math
import os
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

PARAM_KEYS = ("b", "a", "rho", "m_w", "m_T", "I_alpha", "c_alpha", "c_h", "k_alpha",
              "k_alpha2", "k_alpha3", "k_h", "x_alpha")

NOMINAL = dict(b=0.15, a=-0.5, rho=1.204, m_w=5.3, m_T=16.9, I_alpha=0.1726,
               c_alpha=1.0338, c_h=15.4430, k_alpha=60.291, k_alpha2=774.7,
               k_alpha3=3490.7, k_h=3317.8, x_alpha=0.234)

DEFAULT_AUTO_DIR = "/usr/lib/auto-07p"
_TIMEOUT_S = 600


class AutoReferenceError(RuntimeError):
    """AUTO ran but did not produce what was asked for (no Hopf point in range, a failed run)."""


# --------------------------------------------------------------------------------------------
# availability
# --------------------------------------------------------------------------------------------

def _auto_dir() -> str:
    return os.environ.get("AUTO_DIR") or DEFAULT_AUTO_DIR


def _auto_objects(auto_dir: str) -> list[str]:
    return sorted(glob.glob(os.path.join(auto_dir, "lib", "*.o")))


def _fortran_compiler() -> str | None:
    fc = os.environ.get("FC")
    if fc and shutil.which(fc):
        return shutil.which(fc)
    return shutil.which("gfortran")


_SMOKE_F90 = """\
SUBROUTINE FUNC(NDIM,U,ICP,PAR,IJAC,F,DFDU,DFDP)
  IMPLICIT NONE
  INTEGER, INTENT(IN) :: NDIM, ICP(*), IJAC
  DOUBLE PRECISION, INTENT(IN) :: U(NDIM), PAR(*)
  DOUBLE PRECISION, INTENT(OUT) :: F(NDIM)
  DOUBLE PRECISION, INTENT(INOUT) :: DFDU(NDIM,NDIM), DFDP(NDIM,*)
  F(1) = PAR(1) - U(1)
END SUBROUTINE FUNC
SUBROUTINE STPNT(NDIM,U,PAR,T)
  IMPLICIT NONE
  INTEGER, INTENT(IN) :: NDIM
  DOUBLE PRECISION, INTENT(INOUT) :: U(NDIM), PAR(*)
  DOUBLE PRECISION, INTENT(IN) :: T
  PAR(1) = 0.0D0
  U(1) = 0.0D0
END SUBROUTINE STPNT
SUBROUTINE BCND
END SUBROUTINE BCND
SUBROUTINE ICND
END SUBROUTINE ICND
SUBROUTINE FOPT
END SUBROUTINE FOPT
SUBROUTINE PVLS
END SUBROUTINE PVLS
"""


@functools.lru_cache(maxsize=1)
def auto_unavailable_reason() -> str | None:
    """None when AUTO-07p can build and run an equations file here, else why not."""
    auto_dir = _auto_dir()
    if not _auto_objects(auto_dir):
        return (f"AUTO-07p library objects not found in {auto_dir}/lib "
                "(install: apt-get install -y auto-07p gfortran; or set AUTO_DIR)")
    if _fortran_compiler() is None:
        return ("gfortran not found: AUTO-07p needs a Fortran compiler to build equations "
                "files (apt-get install -y gfortran)")
    try:
        with tempfile.TemporaryDirectory(prefix="auto07p_smoke_") as d:
            Path(d, "smoke.f90").write_text(_SMOKE_F90)
            _build(Path(d), "smoke")
            out = _run_auto(Path(d), "smoke",
                            "NDIM=1, IPS=1, ILP=0, ICP=[1], ISP=0, NMX=5, DS=0.1, "
                            "DSMIN=0.01, DSMAX=0.1, JAC=0\n")
            if not (Path(d) / "fort.7").exists():
                return "AUTO-07p smoke run produced no output: " + out[-500:]
    except Exception as exc:  # noqa: BLE001 -- any failure means "not usable here"
        return f"AUTO-07p smoke build/run failed: {exc}"
    return None


def auto_available() -> bool:
    return auto_unavailable_reason() is None


def auto_version() -> str:
    """'AUTO-07p <version>' from the Debian package database when installed that way."""
    auto_dir = _auto_dir()
    if os.path.realpath(auto_dir) == DEFAULT_AUTO_DIR and shutil.which("dpkg-query"):
        r = subprocess.run(["dpkg-query", "-W", "-f=${Version}", "auto-07p"],
                           capture_output=True, text=True)
        if r.returncode == 0 and r.stdout.strip():
            v = r.stdout.strip()
            return f"AUTO-07p {v.split('+')[0]} (Debian auto-07p {v})"
    return f"AUTO-07p (AUTO_DIR={auto_dir}, version unknown)"


# --------------------------------------------------------------------------------------------
# build / run
# --------------------------------------------------------------------------------------------

def _build(workdir: Path, name: str) -> None:
    fc = _fortran_compiler()
    if fc is None:
        raise AutoReferenceError("no Fortran compiler (gfortran) found")
    objs = _auto_objects(_auto_dir())
    # Same flags AUTO's cmds.make uses (the library is built with -fopenmp).
    flags = ["-O2", "-fPIC", "-std=legacy", "-fopenmp"]
    for cmd in ([fc, *flags, "-c", f"{name}.f90", "-o", f"{name}.o"],
                [fc, *flags, f"{name}.o", *objs, "-o", f"{name}.exe"]):
        r = subprocess.run(cmd, cwd=workdir, capture_output=True, text=True,
                           timeout=_TIMEOUT_S)
        if r.returncode != 0:
            raise AutoReferenceError(f"{' '.join(cmd[:3])}... failed:\n{r.stderr[-2000:]}")


def _run_auto(workdir: Path, name: str, constants: str, restart: str | None = None) -> str:
    """Run ``name.exe`` with the constants on stdin (and ``s.<restart>`` as start data)."""
    for f in ("fort.7", "fort.8", "fort.9"):
        (workdir / f).unlink(missing_ok=True)
    stdin = (f"s='{restart}'\n" if restart else "") + constants
    env = dict(os.environ)
    env.setdefault("OMP_NUM_THREADS", "1")
    r = subprocess.run([f"./{name}.exe"], input=stdin, cwd=workdir, capture_output=True,
                       text=True, timeout=_TIMEOUT_S, env=env)
    if r.returncode != 0 or not (workdir / "fort.7").exists():
        raise AutoReferenceError(
            f"AUTO run failed (rc={r.returncode}):\n{r.stdout[-2000:]}\n{r.stderr[-2000:]}")
    return r.stdout


def _save_as(workdir: Path, tag: str) -> None:
    for src, dst in (("fort.7", "b."), ("fort.8", "s."), ("fort.9", "d.")):
        p = workdir / src
        if p.exists():
            p.replace(workdir / (dst + tag))


# --------------------------------------------------------------------------------------------
# equations file
# --------------------------------------------------------------------------------------------

def _dlit(x: float) -> str:
    """A Fortran double precision literal that round-trips ``x`` exactly."""
    x = float(x)
    if not math.isfinite(x):
        raise ValueError(f"non-finite parameter value {x!r}")
    return f"{x:.17e}".replace("e", "D")


_FUNC_BODY = """\
  V = PAR(1)
  H = U(1); AL = U(2); HD = U(3); AD = U(4)
  ! structural + added mass (independent of V) and its inverse
  M11 = MT + RHO*PI*BB**2
  M12 = MW*XA*BB - RHO*PI*BB**3*AA
  M22 = IA + RHO*PI*BB**4*(1.0D0/8.0D0 + AA**2)
  DET = M11*M22 - M12*M12
  MI11 = M22/DET
  MI12 = -M12/DET
  MI22 = M11/DET
  ! damping B = B0 + V*DB, stiffness S = S0 + V**2*DS
  DB11 = 2.0D0*PI*RHO*BB
  DB12 = 2.0D0*PI*RHO*BB**2*(1.0D0 - AA)
  DB21 = -2.0D0*PI*RHO*BB**2*(AA + 0.5D0)
  DB22 = -2.0D0*AA*RHO*PI*BB**3*(0.5D0 - AA)
  B11 = CH + DB11*V
  B12 = DB12*V
  B21 = DB21*V
  B22 = CA + DB22*V
  DS12 = 2.0D0*PI*RHO*BB
  DS22 = -2.0D0*PI*RHO*BB**2*(0.5D0 + AA)
  S11 = KH
  S12 = DS12*V**2
  S21 = 0.0D0
  S22 = KA + DS22*V**2
  R1 = B11*HD + B12*AD + S11*H + S12*AL
  R2 = B21*HD + B22*AD + S21*H + S22*AL + KA2*AL**2 + KA3*AL**3
  F(1) = HD
  F(2) = AD
  F(3) = -(MI11*R1 + MI12*R2)
  F(4) = -(MI12*R1 + MI22*R2)
  IF (IJAC == 0) RETURN
  DFN = S22 + 2.0D0*KA2*AL + 3.0D0*KA3*AL**2
  DFDU(:,:) = 0.0D0
  DFDU(1,3) = 1.0D0
  DFDU(2,4) = 1.0D0
  DFDU(3,1) = -(MI11*S11 + MI12*S21)
  DFDU(3,2) = -(MI11*S12 + MI12*DFN)
  DFDU(3,3) = -(MI11*B11 + MI12*B21)
  DFDU(3,4) = -(MI11*B12 + MI12*B22)
  DFDU(4,1) = -(MI12*S11 + MI22*S21)
  DFDU(4,2) = -(MI12*S12 + MI22*DFN)
  DFDU(4,3) = -(MI12*B11 + MI22*B21)
  DFDU(4,4) = -(MI12*B12 + MI22*B22)
  IF (IJAC == 1) RETURN
  DFDP(:,1) = 0.0D0
  R1 = DB11*HD + DB12*AD + 2.0D0*V*DS12*AL
  R2 = DB21*HD + DB22*AD + 2.0D0*V*DS22*AL
  DFDP(3,1) = -(MI11*R1 + MI12*R2)
  DFDP(4,1) = -(MI12*R1 + MI22*R2)
"""

_FORTRAN_NAMES = dict(b="BB", a="AA", rho="RHO", m_w="MW", m_T="MT", I_alpha="IA",
                      c_alpha="CA", c_h="CH", k_alpha="KA", k_alpha2="KA2", k_alpha3="KA3",
                      k_h="KH", x_alpha="XA")


def equations_f90(params: dict, v_start: float) -> str:
    """The AUTO-07p equations file (free-form Fortran) for the given parameter values."""
    consts = "\n".join(f"  DOUBLE PRECISION, PARAMETER :: {_FORTRAN_NAMES[k]} = {_dlit(params[k])}"
                       for k in PARAM_KEYS)
    return f"""\
! Quasi-steady 2-DoF aerofoil flutter model; U = (h, alpha, h', alpha'), PAR(1) = V.
! Generated by tests/auto07p_reference.py.
SUBROUTINE FUNC(NDIM,U,ICP,PAR,IJAC,F,DFDU,DFDP)
  IMPLICIT NONE
  INTEGER, INTENT(IN) :: NDIM, ICP(*), IJAC
  DOUBLE PRECISION, INTENT(IN) :: U(NDIM), PAR(*)
  DOUBLE PRECISION, INTENT(OUT) :: F(NDIM)
  DOUBLE PRECISION, INTENT(INOUT) :: DFDU(NDIM,NDIM), DFDP(NDIM,*)
  DOUBLE PRECISION, PARAMETER :: PI = 3.14159265358979323846264338D0
{consts}
  DOUBLE PRECISION :: V, H, AL, HD, AD, M11, M12, M22, DET, MI11, MI12, MI22
  DOUBLE PRECISION :: B11, B12, B21, B22, S11, S12, S21, S22
  DOUBLE PRECISION :: DB11, DB12, DB21, DB22, DS12, DS22, R1, R2, DFN
{_FUNC_BODY}END SUBROUTINE FUNC

SUBROUTINE STPNT(NDIM,U,PAR,T)
  IMPLICIT NONE
  INTEGER, INTENT(IN) :: NDIM
  DOUBLE PRECISION, INTENT(INOUT) :: U(NDIM), PAR(*)
  DOUBLE PRECISION, INTENT(IN) :: T
  PAR(1) = {_dlit(v_start)}
  U(:) = 0.0D0
END SUBROUTINE STPNT

SUBROUTINE BCND
END SUBROUTINE BCND
SUBROUTINE ICND
END SUBROUTINE ICND
SUBROUTINE FOPT
END SUBROUTINE FOPT
SUBROUTINE PVLS
END SUBROUTINE PVLS
"""


def _constants(**kw) -> str:
    base = dict(NDIM=4, IPS=1, IRS=0, ILP=0, ICP="[1]", NTST=50, NCOL=4, IAD=3, ISP=2,
                ISW=1, IPLT=0, NBC=0, NINT=0, NMX=1000, NPR=0, MXBF=0, IID=2, ITMX=20,
                ITNW=8, NWTN=3, JAC=1, EPSL=1e-10, EPSU=1e-10, EPSS=1e-8, DS=0.1,
                DSMIN=1e-8, DSMAX=0.5, IADS=1, NPAR=12, THU="{}")
    base.update(kw)
    return "\n".join(f"{k}={v}" for k, v in base.items()) + "\n"


# --------------------------------------------------------------------------------------------
# output parsing
# --------------------------------------------------------------------------------------------

def _read_s_file(path: Path) -> list[dict]:
    """Parse an AUTO-07p solution file (s.xxx / fort.8) into a list of labelled solutions."""
    lines = path.read_text().splitlines()
    sols, i = [], 0
    while i < len(lines):
        head = lines[i].split()
        if not head:
            i += 1
            continue
        ibr, ntot, itp, lab, nfpr, isw, ntpl, nar, nrowpr, ntst, ncol, npar = map(int, head[:12])
        toks = " ".join(lines[i + 1:i + 1 + nrowpr]).replace("D", "E").split()
        vals, k = toks, 0

        def take(n):
            nonlocal k
            out = vals[k:k + n]
            k += n
            return out
        tab = np.array(take(ntpl * nar), float).reshape(ntpl, nar)
        icp = [int(x) for x in take(nfpr)]
        take(nfpr)                          # parameter part of the branch direction
        take(ntpl * (nar - 1))              # state part of the branch direction
        par = np.array(take(npar), float)
        sols.append(dict(ibr=ibr, pt=ntot, itp=itp, lab=lab, icp=icp, ntst=ntst, ncol=ncol,
                         t=tab[:, 0], u=tab[:, 1:], par=par))
        i += 1 + nrowpr
    return sols


def _type(sol) -> int:
    return abs(sol["itp"]) % 10     # 3 = HB, 5 = LP, 9 = EP, 4 = UZ


def _orbit_measures(sol, comp: int) -> dict:
    """Half peak-to-peak and first-harmonic amplitude of state ``comp`` of a periodic solution,
    evaluated on AUTO's own piecewise polynomial (degree NCOL on each of the NTST intervals;
    the s-file holds it at NCOL+1 equispaced points per interval)."""
    t, y, ncol, ntst = sol["t"], sol["u"][:, comp], sol["ncol"], sol["ntst"]
    ymax, ymin = -np.inf, np.inf
    xg, wg = np.polynomial.legendre.leggauss(12)
    c1 = 0.0 + 0.0j
    for j in range(ntst):
        tj, yj = t[j * ncol:(j + 1) * ncol + 1], y[j * ncol:(j + 1) * ncol + 1]
        t0, t1 = tj[0], tj[-1]
        s = (tj - t0) / (t1 - t0)
        poly = np.polynomial.Polynomial.fit(s, yj, ncol, domain=[0, 1], window=[0, 1])
        cand = [0.0, 1.0] + [r.real for r in poly.deriv().roots()
                             if abs(r.imag) < 1e-12 and 0.0 <= r.real <= 1.0]
        vals = poly(np.array(cand))
        ymax, ymin = max(ymax, vals.max()), min(ymin, vals.min())
        sq = 0.5 * (xg + 1.0)
        tq = t0 + (t1 - t0) * sq
        c1 += 0.5 * (t1 - t0) * np.sum(wg * poly(sq) * np.exp(-2j * np.pi * tq))
    return dict(half_peak_to_peak=0.5 * (ymax - ymin), first_harmonic=2.0 * abs(c1),
                max=ymax, min=ymin)


# --------------------------------------------------------------------------------------------
# the reference computation
# --------------------------------------------------------------------------------------------

def _periodic_run(wd: Path, hb_label: int, v_range, ntst: int, tag: str) -> dict | None:
    lo, hi = v_range
    span = hi - lo
    c = _constants(IPS=2, IRS=hb_label, ILP=1, ICP="[1, 11]", NTST=ntst, NCOL=4, ISP=2,
                   NMX=2000, DS=0.01, DSMIN=1e-8, DSMAX=max(span / 50.0, 0.05),
                   THL="{11: 0.0}", STOP="['LP1']", UZSTOP=f"{{1: [{lo!r}, {hi!r}]}}")
    (wd / f"c.{tag}").write_text(c)
    _run_auto(wd, "flutter", c, restart="eq")
    _save_as(wd, tag)
    lps = [s for s in _read_s_file(wd / f"s.{tag}") if _type(s) == 5]
    if not lps:
        return None
    lp = lps[0]
    h, al = _orbit_measures(lp, 0), _orbit_measures(lp, 1)
    period = lp["par"][10]
    return dict(V=float(lp["par"][0]), period=float(period), h=h, alpha=al)


def auto_flutter_reference(params: dict, v_range=(5.0, 40.0), workdir=None, ntst: int = 60
                           ) -> dict:
    """Hopf point and first fold of limit cycles of the flutter model, computed by AUTO-07p.

    ``params`` needs the keys in :data:`PARAM_KEYS` (extra keys are ignored).  Returns::

        hopf_V, hopf_freq_hz        first Hopf point on the trivial equilibrium for V in v_range
                                    (frequency = 1/PAR(11) = Im(lambda)/2pi at the HB)
        fold_V                      V at the first fold (LP) of the periodic family born at that
                                    Hopf point, or None if the family leaves v_range first
                                    (e.g. a supercritical Hopf without a fold in range)
        fold_amplitude_h            heave amplitude at the fold as HALF PEAK-TO-PEAK,
                                    (max h - min h)/2 (m), evaluated on AUTO's collocation
                                    polynomials; None with fold_V
        fold_amplitude_h_first_harmonic   2|c_1| of h(t) at the fold (m)
        fold_amplitude_alpha, fold_amplitude_alpha_first_harmonic   same for alpha (rad)
        fold_freq_hz                1/period at the fold
        fold_V_coarse, fold_rel_change, fold_amplitude_h_coarse
                                    the NTST=ntst run, vs the returned NTST=2*ntst one
        all_hopf_V                  every HB found on the equilibrium branch in v_range
        origin_stable_at_v_min      False means the first HB in range is not the flutter onset
        hopf_subcritical            True when the periodic family leaves the HB towards V < hopf_V
        auto_version, runtime_s, workdir (None when a temporary directory was used)

    Values come from AUTO's files (11 significant digits).  Tolerances: EPSL = EPSU = 1e-10, EPSS = 1e-8, JAC = 1 (analytic derivatives); the periodic
    family is computed with NCOL = 4 and NTST = ntst and 2*ntst.  Raises
    :class:`AutoReferenceError` when no Hopf point lies in ``v_range`` or a run fails.
    """
    missing = [k for k in PARAM_KEYS if k not in params]
    if missing:
        raise KeyError(f"missing flutter parameters: {missing}")
    reason = auto_unavailable_reason()
    if reason is not None:
        raise AutoReferenceError(reason)
    lo, hi = float(v_range[0]), float(v_range[1])
    if not hi > lo:
        raise ValueError(f"bad v_range {v_range!r}")
    t_start = time.perf_counter()
    tmp = None
    if workdir is None:
        tmp = tempfile.TemporaryDirectory(prefix="auto07p_flutter_")
        wd = Path(tmp.name)
    else:
        wd = Path(workdir)
        wd.mkdir(parents=True, exist_ok=True)
    try:
        (wd / "flutter.f90").write_text(equations_f90(params, lo))
        _build(wd, "flutter")

        # 1. trivial equilibrium in V -> HB
        c_eq = _constants(IPS=1, IRS=0, ILP=0, ICP="[1]", ISP=2, NMX=5000,
                          DS=(hi - lo) / 200.0, DSMIN=1e-8, DSMAX=(hi - lo) / 50.0,
                          UZSTOP=f"{{1: {hi!r}}}")
        (wd / "c.eq").write_text(c_eq)
        _run_auto(wd, "flutter", c_eq)
        _save_as(wd, "eq")
        hbs = [s for s in _read_s_file(wd / "s.eq") if _type(s) == 3]
        hbs = [s for s in hbs if lo <= s["par"][0] <= hi]
        if not hbs:
            raise AutoReferenceError(
                f"no Hopf point on the trivial equilibrium for V in [{lo}, {hi}]")
        hb = min(hbs, key=lambda s: s["par"][0])
        # AUTO prints stable points with a negative point number
        eq_rows = [ln.split() for ln in (wd / "b.eq").read_text().splitlines()]
        eq_rows = [r for r in eq_rows if len(r) > 5 and r[0] != "0"]
        stable_at_lo = bool(eq_rows) and int(eq_rows[0][1]) < 0
        hopf_V = float(hb["par"][0])
        hopf_freq = 1.0 / float(hb["par"][10])

        # 2. periodic family from the HB -> LP, at two mesh sizes
        coarse = _periodic_run(wd, hb["lab"], (lo, hi), ntst, "po_coarse")
        fine = _periodic_run(wd, hb["lab"], (lo, hi), 2 * ntst, "po")
        # direction in which the periodic family leaves the HB (second point of b.po)
        rows = [ln.split() for ln in (wd / "b.po").read_text().splitlines()]
        rows = [r for r in rows if len(r) > 5 and r[0] != "0"]
        first_V = float(rows[1][4]) if len(rows) > 1 else None
        out = dict(hopf_V=hopf_V, hopf_freq_hz=hopf_freq,
                   all_hopf_V=[float(s["par"][0]) for s in hbs],
                   origin_stable_at_v_min=stable_at_lo,
                   hopf_subcritical=(None if first_V is None else bool(first_V < hopf_V)),
                   fold_V=None, fold_amplitude_h=None, fold_amplitude_h_first_harmonic=None,
                   fold_amplitude_alpha=None, fold_amplitude_alpha_first_harmonic=None,
                   fold_freq_hz=None, fold_V_coarse=None, fold_rel_change=None,
                   fold_amplitude_h_coarse=None,
                   fold_amplitude_h_kind="half_peak_to_peak",
                   auto_version=auto_version())
        if fine is not None:
            out.update(fold_V=fine["V"], fold_freq_hz=1.0 / fine["period"],
                       fold_amplitude_h=fine["h"]["half_peak_to_peak"],
                       fold_amplitude_h_first_harmonic=fine["h"]["first_harmonic"],
                       fold_amplitude_alpha=fine["alpha"]["half_peak_to_peak"],
                       fold_amplitude_alpha_first_harmonic=fine["alpha"]["first_harmonic"])
            if coarse is not None:
                out.update(fold_V_coarse=coarse["V"],
                           fold_rel_change=abs(coarse["V"] - fine["V"]) / abs(fine["V"]),
                           fold_amplitude_h_coarse=coarse["h"]["half_peak_to_peak"])
        out["runtime_s"] = time.perf_counter() - t_start
        out["workdir"] = None if tmp is not None else str(wd)
        return out
    finally:
        if tmp is not None:
            tmp.cleanup()


# --------------------------------------------------------------------------------------------
# independent numpy check of the Hopf point
# --------------------------------------------------------------------------------------------

def _np_jacobian(p: dict, V: float) -> np.ndarray:
    b, a, rho, pi = p["b"], p["a"], p["rho"], np.pi
    m12 = p["m_w"] * p["x_alpha"] * b - rho * pi * b ** 3 * a
    M = np.array([[p["m_T"] + rho * pi * b ** 2, m12],
                  [m12, p["I_alpha"] + rho * pi * b ** 4 * (1 / 8 + a ** 2)]])
    B = np.array([[p["c_h"] + 2 * pi * rho * b * V, 2 * pi * rho * b ** 2 * V * (1 - a)],
                  [-2 * pi * rho * b ** 2 * V * (a + 0.5),
                   p["c_alpha"] - 2 * a * rho * pi * b ** 3 * V * (0.5 - a)]])
    S = np.array([[p["k_h"], 2 * pi * rho * b * V ** 2],
                  [0.0, p["k_alpha"] - 2 * pi * rho * b ** 2 * V ** 2 * (0.5 + a)]])
    Minv = np.linalg.inv(M)
    return np.block([[np.zeros((2, 2)), np.eye(2)], [-Minv @ S, -Minv @ B]])


def eigen_hopf(params: dict, v_range=(5.0, 40.0), n_scan: int = 400) -> tuple[float, float]:
    """(V, frequency in Hz) of the first Hopf point in v_range: the first V where the largest
    real part of the linearisation's eigenvalues at the origin crosses zero (scan + brentq)."""
    from scipy.optimize import brentq

    def growth(V):
        return float(np.max(np.linalg.eigvals(_np_jacobian(params, V)).real))

    vs = np.linspace(v_range[0], v_range[1], n_scan + 1)
    g = [growth(v) for v in vs]
    for v0, v1, g0, g1 in zip(vs[:-1], vs[1:], g[:-1], g[1:]):
        if g0 < 0.0 <= g1:
            Vh = brentq(growth, v0, v1, xtol=1e-14, rtol=1e-15, maxiter=200)
            ev = np.linalg.eigvals(_np_jacobian(params, Vh))
            return Vh, abs(ev[np.argmax(ev.real)].imag) / (2 * np.pi)
    raise ValueError(f"no Hopf crossing in {v_range}")
