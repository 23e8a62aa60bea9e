"""What a fit takes, as typed objects that check themselves when built: :class:`TrainConfig`
(how one correction is trained: network, optimiser, shooting weights, penalties) inside
:class:`FitOptions` (the whole fit: system, approximator, starts, adequacy, references).
A ValueError from either names the option (in the command line's spelling) and what is
wrong with it; the command line prints it as its one-line usage error.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import asdict, dataclass

import numpy as np

from .._systems import system_kind
from ..models.library import effect, effect_choice
from ..models.mechanistic import SYSTEMS
from ..models.parameter_file import MechanisticParameters
from .control import ControlChoice
from .penalties import Penalty
from .sensor_zero import AUTO, SENSOR_ZERO_CHOICES

APPROXIMATORS = ("nn", "gp")
TRAININGS = ("trajectory", "periodic")
MECHANISTIC = ("equation", "periodic")
# guide rounds for a start whose diagram has folds the adequacy rule does not allow or
# misses a measured point (ude_fit.guide_rounds), by default:
# the first at the guide weight, the second at three times it (on lee2020 seeds 0-2 a
# second round ran in 7 starts and was the one kept in 1; docs/fitting.md)
DEFAULT_GUIDE_ROUNDS = 2
# random starts of a fit: the adequate ones' medoid is kept (analysis.keep), so many starts
# make the kept model the consensus of many; on the aerofoil a start costs about a third of
# what it did before collocation (docs/fitting.md), and 16 take less time than 5 did
DEFAULT_STARTS = 16


@dataclass(frozen=True)
class TrainConfig:
    """How one correction is trained: the network, the optimiser's steps, the shooting
    losses' weights and the penalties (:mod:`.penalties`). A field left at None takes its
    system's default (:data:`SYSTEM_DEFAULTS`, applied by :meth:`for_system`). Checks its
    own fields when built (ValueError naming the field)."""
    width: int = 12
    depth: int = 2
    equation_steps: int | None = None         # Adam steps on the equation loss
    equation_lbfgs_steps: int | None = None   # L-BFGS steps on the equation loss
    adam_steps: int | None = None             # Adam steps on the trajectory/periodic loss
    lbfgs_steps: int | None = None            # L-BFGS steps on the trajectory/periodic loss
    learning_rate: float = 3e-3
    substeps: int | None = None  # RK4 steps between two samples of the orbit
    closure_weight: float = 10.0
    stability_weight: float = 10.0
    stability_margin: float = 0.02
    init_scale: float = 1e-2
    param_scale: float = 1.0     # the parameter input is standardised by this times its spread
    # how the NN correction depends on the parameter: "input" (a network input like the
    # states) or "polynomial" (a polynomial of param_degree in it, state-dependent
    # coefficients; PolynomialParamCorrection)
    param_dependence: str = "input"
    param_degree: int = 2
    # the network cannot move the equilibrium at rest or its linearisation; explicit linear
    # terms carry the linear change (RestFreeCorrection; aerofoil only; None: the system's
    # default, on for the aerofoil's network)
    rest_free: bool | None = None
    # "network": a neural network of the states and the parameter; "amplitude": linear
    # terms plus a damping convex in the oscillation's size (models.amplitude; aerofoil
    # only, experimental; docs/fitting.md)
    form: str = "network"
    penalties: tuple[Penalty, ...] = ()
    # aerofoil, periodic training: at most this many rounds of training on with the broken
    # constraints' penalties, weighted by the data's misfit
    # (training.rounds.enforce_constraints; 0: none; None: the system's default, 7 for the
    # aerofoil where they apply: FitOptions.applied)
    constraint_rounds: int | None = None
    # Adam steps before each constraint round's L-BFGS steps (0: L-BFGS alone, from where the
    # trained start is; Adam restarted there first moves every weight by about its learning
    # rate: docs/experiments.md, twenty-seventh session)
    constraint_adam_steps: int = 0
    # the constraint rounds hold the unstable-branch condition too (penalties.UnstableBranch:
    # the model's branch falls in airspeed as its amplitude grows all along the unstable
    # stretch the data shows; experimental, off by default: docs/fitting.md)
    constrain_unstable_branch: bool = False
    # aerofoil, periodic training: rounds of training on with the measured orbits asked to
    # lie on the branch from the Hopf point, one turn at most (training.branch; 0: none)
    branch_rounds: int = 0
    # aerofoil, periodic training: rounds of training on with the branch monotone between
    # orbits of the same stability and rising above the largest stable one
    # (training.monotone; 0: none)
    monotone_rounds: int = 0
    # aerofoil, periodic training: before the periodic stage on every orbit, stages on the
    # orbit nearest the Hopf point alone, then one more at a time in the order a branch
    # with one fold meets them (training.branch.amplitude_stages)
    amplitude_stages: bool = False
    # periodic training: every orbit's parameter an unknown too, with a prior whose scales
    # are the data's own scatter (training.parameter_errors; experimental, off by default)
    parameter_errors: bool = False
    # periodic training: each labelled orbit's stability margin predicted by the points'
    # Hopf normal-form backbone and its branch's line, stability_margin where they predict
    # none
    # (analysis.margins; None: the fit's default, on for the aerofoil's network trained on
    # periodic orbits: FitOptions._defaults_that_apply; off in a training called directly)
    backbone_margins: bool | None = None
    # no equation stage: each start's first training (periodic or trajectory) begins at the
    # mechanistic model (the fresh network's last layer is small) and takes
    # start_adam_steps and start_lbfgs_steps, as it has the whole correction to learn; the
    # rounds after it keep adam_steps and lbfgs_steps (None: as backbone_margins;
    # docs/fitting.md)
    from_mechanistic: bool | None = None
    start_adam_steps: int = 3000
    start_lbfgs_steps: int = 600
    # periodic training: a start's first training (with from_mechanistic the long one) on
    # every orbit collocated (training.collocation: the orbit a Fourier series)
    # instead of shot, then the periodic stage's adam_steps and lbfgs_steps by shooting from
    # where it left the orbits (None: as from_mechanistic; docs/fitting.md)
    collocation: bool | None = None
    # where collocation's series come from, a plan (training.collocation.PLANS): "free",
    # unknowns of the optimiser beside the model; "solved" for the model at every
    # evaluation (variable projection, training.projection: a step costs about twice a
    # free one's; on noisy simulated campaigns it does not end where free series lag the
    # network); "free-then-solved", free for the first Adam steps (FREE_LEAD of them: the
    # mechanistic model's orbits may lie far from the measured ones), solved after them
    # (None: the last; docs/fitting.md)
    collocation_series: str | None = None

    def __post_init__(self):
        for name in ("width", "depth"):
            _check_int(name, getattr(self, name), 1)
        _check_int("param_degree", self.param_degree, 0)
        if self.constraint_rounds is not None:
            _check_int("constraint_rounds", self.constraint_rounds, 0)
        _check_int("constraint_adam_steps", self.constraint_adam_steps, 0)
        for name in ("constrain_unstable_branch", "parameter_errors"):
            _check_bool(name, getattr(self, name))
        for name in ("backbone_margins", "from_mechanistic", "collocation"):  # None: default
            _check_bool(name, getattr(self, name), none_ok=True)
        _check_int("start_adam_steps", self.start_adam_steps, 0)
        _check_int("start_lbfgs_steps", self.start_lbfgs_steps, 0)
        _check_int("branch_rounds", self.branch_rounds, 0)
        _check_int("monotone_rounds", self.monotone_rounds, 0)
        for name in ("equation_steps", "equation_lbfgs_steps", "adam_steps", "lbfgs_steps"):
            if getattr(self, name) is not None:
                _check_int(name, getattr(self, name), 0)
        if self.substeps is not None:
            _check_int("substeps", self.substeps, 1)
        for name in ("learning_rate", "init_scale", "param_scale"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive number, not {v!r}")
        for name in ("closure_weight", "stability_weight", "stability_margin"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be a number at least 0, not {v!r}")
        if self.param_dependence not in PARAM_DEPENDENCE:
            raise ValueError(f"param_dependence must be input or polynomial, not "
                             f"{self.param_dependence!r}")
        if self.form not in FORMS:
            raise ValueError(f"form must be {' or '.join(FORMS)}, not {self.form!r}")
        if self.collocation_series not in (None, *COLLOCATION_SERIES):
            raise ValueError(f"collocation_series must be {', '.join(COLLOCATION_SERIES)}, "
                             f"not {self.collocation_series!r}")
        if self.form == "amplitude" and (self.rest_free or self.param_dependence != "input"):
            raise ValueError("--correction-form amplitude has its own linear terms and no "
                             "network: not with --rest-free or --param-dependence polynomial")
        _check_bool("rest_free", self.rest_free, none_ok=True)
        _check_bool("amplitude_stages", self.amplitude_stages)
        object.__setattr__(self, "penalties", tuple(self.penalties))
        kinds = [type(p) for p in self.penalties]
        for p in self.penalties:
            if not isinstance(p, Penalty):
                raise ValueError(f"penalties must be Penalty objects, not {p!r}")
        if len(set(kinds)) != len(kinds):
            raise ValueError("penalties: each kind at most once")

    def for_system(self, system: str) -> "TrainConfig":
        """This configuration with every None field set to ``system``'s default."""
        if system not in SYSTEM_DEFAULTS:
            raise ValueError(f"unknown system {system!r} (flutter or oscillator)")
        defaults = dict(SYSTEM_DEFAULTS[system])
        if self.form != "network":          # the amplitude form has its own linear terms
            defaults["rest_free"] = False
        cfg = dataclasses.replace(self, **{k: v for k, v in defaults.items()
                                           if getattr(self, k) is None})
        if cfg.collocation_series is None:
            cfg = dataclasses.replace(cfg, collocation_series=DEFAULT_COLLOCATION_SERIES)
        if cfg.equation_lbfgs_steps is None:
            cfg = dataclasses.replace(cfg, equation_lbfgs_steps=cfg.lbfgs_steps)
        # the fit's defaults for these (FitOptions) depend on more than the system; a
        # training called directly does without them unless asked
        return dataclasses.replace(cfg, **{k: False for k in ("backbone_margins",
                                                              "from_mechanistic",
                                                              "collocation")
                                           if getattr(cfg, k) is None})

    def penalty(self, kind: type) -> Penalty | None:
        """The penalty of class ``kind``, if any."""
        return next((p for p in self.penalties if isinstance(p, kind)), None)

    def needs_points(self) -> bool:
        """Whether any active penalty reads the regularity points."""
        return (any(p.needs_points and p.weight for p in self.penalties)
                or bool(self.constraint_rounds) or self.branch_rounds > 0
                or self.monotone_rounds > 0)

    def to_json(self) -> dict:
        d = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)
             if f.name != "penalties"}
        d["penalties"] = {k: v for p in self.penalties for k, v in p.to_json().items()}
        return d


def _check_bool(name: str, v, none_ok: bool = False) -> None:
    if not (isinstance(v, bool) or (none_ok and v is None)):
        raise ValueError(f"{name} must be True or False, not {v!r}")


def _check_int(name: str, v, least: int) -> None:
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < least:
        raise ValueError(f"{name} must be an integer at least {least}, not {v!r}")


PARAM_DEPENDENCE = ("input", "polynomial")
FORMS = ("network", "amplitude")
# the keys of training.collocation.PLANS (which imports this module)
COLLOCATION_SERIES = ("free", "solved", "free-then-solved")
DEFAULT_COLLOCATION_SERIES = "free-then-solved"

# Per-system defaults. The aerofoil's network is rest-free (the Hopf point is the
# mechanistic model's and explicit linear terms', not the network's extrapolation to rest)
# and its periodic fit is held to the energy-rising and rest-stability conditions by up to 7
# constraint rounds (docs/fitting.md: on every flutter dataset measured, simulated and
# lee2020, the pair is no worse than the plain network in adequate starts, and its Hopf
# points lie within 0.8 m/s of the truth where the plain network's strayed by up to 14 m/s).
# The forced oscillator's orbits are smooth enough at 64 RK4 steps per
# period (2 per sample; amplitude within 1e-5 of the converged orbit up to 10 mm), which
# makes its shooting losses 3x cheaper; its correction is cheap to fit to the equation
# residual, and that first stage decides most of the final quality, so it gets more steps.
SYSTEM_DEFAULTS = {
    "flutter": dict(equation_steps=1500, adam_steps=300, lbfgs_steps=100, substeps=4,
                    rest_free=True, constraint_rounds=7),
    "oscillator": dict(equation_steps=4000, equation_lbfgs_steps=1000, adam_steps=300,
                       lbfgs_steps=100, substeps=2, rest_free=False, constraint_rounds=0),
}


@dataclass(frozen=True)
class FitOptions:
    """Everything a fit takes, checked when built: a ValueError names the option (in the
    command line's spelling) and what is wrong with it."""
    system: str
    approximator: str = "nn"
    training: str = "periodic"
    starts: int = DEFAULT_STARTS
    # the NN starts trained together (training/optimise.py: Adam vmapped, L-BFGS one start
    # at a time): the same result per start; on 2 cores 16 starts train 1.3x faster than
    # one after another (benchmarks/ude_benchmark.py), not the tenfold a GPU would give
    starts_together: bool = False
    seed: int = 0
    samples: int = 32                 # samples per period of each averaged orbit
    train: TrainConfig = TrainConfig()
    adequacy_factor: float = 2.0
    adequacy_floor: float = 0.01
    gp_restarts: int = 2
    mechanistic: str = "equation"     # "equation": least squares; "periodic": then refined
    reference_hopf: float | None = None   # known Hopf airspeed (m/s), for the error figures
    reference_fold: float | None = None   # known fold airspeed (m/s)
    # the user's values for the mechanistic model (--mechanistic-params FILE.toml)
    mechanistic_parameters: MechanisticParameters | None = None
    # the aerofoil's recorded holding control as a known force on heave (training.control);
    # control_gain: N per unit of the record (None: 1 for a record in N, else identified)
    control_input: bool = False
    control_gain: float | None = None
    # library effects added to the mechanistic model as terms of their own, identified with
    # it (--add EFFECT[=SHAPE]): ((key, shape or None), ...); None: chosen from the data
    mechanistic_effects: tuple = ()
    # orbits of a one-fold curve fitted to the points, trained on between and beyond the
    # measured ones (training.guides; experimental, aerofoil), each at guide_weight
    guide_orbits: int = 0
    guide_weight: float = 0.3
    # rounds of training on with the guides for a start whose traced diagram breaks the
    # adequacy rule's fold count or misses a point (ude_fit.guide_rounds; aerofoil), the first at
    # guide_weight; None: DEFAULT_GUIDE_ROUNDS where they apply, else 0
    guide_rounds: int | None = None
    # where the points' rest position comes from when their files do not record it
    # (training.sensor_zero): "own-means" (each point's own mean), "identified", or "auto":
    # the identified one where the mechanistic model meets the points better with it
    sensor_zero: str = AUTO

    def __post_init__(self):
        if self.sensor_zero not in SENSOR_ZERO_CHOICES:
            raise ValueError(f"--sensor-zero must be {', '.join(SENSOR_ZERO_CHOICES)}, not "
                             f"{self.sensor_zero!r}")
        if self.system not in SYSTEMS:
            raise ValueError(f"--system must be {' or '.join(SYSTEMS)}, not {self.system!r}")
        if self.approximator not in APPROXIMATORS:
            raise ValueError(f"--approximator must be nn or gp, not {self.approximator!r}")
        if self.training not in TRAININGS:
            raise ValueError(f"--training must be trajectory or periodic, not "
                             f"{self.training!r}")
        if self.mechanistic not in MECHANISTIC:
            raise ValueError(f"--mechanistic must be equation or periodic, not "
                             f"{self.mechanistic!r}")
        for name, least in (("starts", 1), ("samples", 8), ("gp_restarts", 0)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < least:
                raise ValueError(f"--{name.replace('_', '-')} must be an integer at least "
                                 f"{least}, not {v!r}")
        for name in ("adequacy_factor", "adequacy_floor"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be a number at least 0, not {v!r}")
        mp = self.mechanistic_parameters
        if mp is not None:
            if not isinstance(mp, MechanisticParameters):
                raise ValueError(f"mechanistic_parameters must be MechanisticParameters, not "
                                 f"{mp!r}")
            MechanisticParameters.of(mp.path, self.system, {**mp.known, **mp.fitted})
        if not isinstance(self.train, TrainConfig):
            raise ValueError(f"train must be a TrainConfig, not {self.train!r}")
        for name in ("reference_hopf", "reference_fold"):
            v = getattr(self, name)
            if v is not None and not math.isfinite(v):
                raise ValueError(f"--{name.replace('_', '-')} must be finite, not {v!r}")
        if not system_kind(self.system).autonomous and self.reference():
            raise ValueError("--reference-hopf/--reference-fold apply to --system flutter "
                             "only")
        active = [p for p in self.train.penalties if p.weight]
        aero = [p for p in active if p.aerofoil_only]
        if not system_kind(self.system).autonomous and aero:
            raise ValueError("/".join(f"--{p.option}" for p in aero)
                             + " apply to --system flutter only")
        if not system_kind(self.system).autonomous and self.train.rest_free:
            raise ValueError("--rest-free applies to --system flutter only (a forced "
                             "system has no equilibrium at rest)")
        if self.train.amplitude_stages and (not system_kind(self.system).autonomous
                                            or self.training != "periodic"):
            raise ValueError("--amplitude-stages applies to --system flutter with --training "
                             "periodic only (the orbits of a branch from a Hopf point)")
        if self.train.parameter_errors and (not system_kind(self.system).autonomous
                                            or self.training != "periodic"):
            raise ValueError("--parameter-errors applies to --system flutter with --training "
                             "periodic only (a self-excited system's parameter enters only "
                             "its vector field)")
        if self.train.backbone_margins and (not system_kind(self.system).autonomous
                                            or self.training != "periodic"):
            raise ValueError("--backbone-margins applies to --system flutter with --training "
                             "periodic only (a self-excited branch's Hopf normal form)")
        if self.train.collocation and self.training != "periodic":
            raise ValueError("--collocation applies to --training periodic only (the "
                             "collocated orbits are the periodic objective's)")
        if not system_kind(self.system).autonomous and self.train.form == "amplitude":
            raise ValueError("--correction-form amplitude applies to --system flutter only "
                             "(a self-excited system's orbit sizes)")
        rounds = (("constraint_rounds", "its conditions are an equilibrium's and a "
                   "self-excited branch's"),
                  ("branch_rounds", "a self-excited branch from a Hopf point"),
                  ("monotone_rounds", "a self-excited branch's stability and direction"))
        for name, why in rounds:
            if not getattr(self.train, name):
                continue
            flag = "--" + name.replace("_", "-")
            if not system_kind(self.system).autonomous:
                raise ValueError(f"{flag} applies to --system flutter only ({why})")
            if self.training != "periodic":
                raise ValueError(f"{flag} applies to --training periodic only")
            if self.starts_together:
                raise ValueError(f"{flag} needs the starts trained one at a time (not "
                                 "--starts-together): each start takes its own rounds")
        _check_bool("control_input", self.control_input)
        ControlChoice.of(self.system, self.control_input, self.control_gain)
        effects = []
        for pair in self.mechanistic_effects:
            if not (isinstance(pair, (tuple, list)) and len(pair) == 2):
                raise ValueError(f"mechanistic_effects: (effect, shape or None) pairs, not "
                                 f"{pair!r}")
            pair = effect_choice(self.system, *pair)
            shape_name = effect(self.system, pair[0]).shape_name
            if shape_name and pair[1] is None:
                # (the cross-validated choice is the discovery layer's: ude-fit refine)
                raise ValueError(f"--add {pair[0]}: give its {shape_name} "
                                 f"({pair[0]}=VALUE); ude-fit refine chooses it by "
                                 "cross-validation")
            if any(k == pair[0] for k, _ in effects):
                raise ValueError(f"--add {pair[0]} given twice")
            effects.append(pair)
        object.__setattr__(self, "mechanistic_effects", tuple(effects))
        self._check_guides()
        _check_bool("starts_together", self.starts_together)
        if self.approximator != "nn":
            nn_only = [f"--{p.option}" for p in active]
            if self.starts_together:
                nn_only.append("--starts-together")
            if self.train.rest_free:
                nn_only.append("--rest-free")
            if self.train.constraint_rounds:
                nn_only.append("--constraint-rounds")
            if self.train.branch_rounds:
                nn_only.append("--branch-rounds")
            if self.train.monotone_rounds:
                nn_only.append("--monotone-rounds")
            if self.train.amplitude_stages:
                nn_only.append("--amplitude-stages")
            if self.train.parameter_errors:
                nn_only.append("--parameter-errors")
            if self.train.backbone_margins:
                nn_only.append("--backbone-margins")
            if self.train.from_mechanistic:
                nn_only.append("--from-mechanistic")
            if self.train.collocation:
                nn_only.append("--collocation")
            if self.train.param_scale != 1.0:
                nn_only.append("--param-scale")
            if self.train.form != "network":
                nn_only.append(f"--correction-form {self.train.form}")
            if self.train.param_dependence != "input":
                nn_only.append("--param-dependence polynomial")
            if self.mechanistic_effects:
                nn_only.append("--add")
            if nn_only:
                raise ValueError("/".join(nn_only) + " apply to --approximator nn only")

        object.__setattr__(self, "train", self._defaults_that_apply())
        if self.train.collocation_series is not None and not self.train.collocation:
            raise ValueError(f"--collocation-series {self.train.collocation_series} needs "
                             "collocation (on by default for the aerofoil's network on "
                             "periodic orbits; --collocation elsewhere)")
        # (None here is the system's default, 7 rounds: _defaults_that_apply set it to 0
        # where the rounds do not apply)
        if self.train.constrain_unstable_branch and self.train.constraint_rounds == 0:
            raise ValueError("--constrain-unstable-branch needs the constraint rounds "
                             "(--constraint-rounds N with N > 0; the aerofoil's network "
                             "trained on periodic orbits one start at a time has 7)")

    def _check_guides(self):
        n, w, r = self.guide_orbits, self.guide_weight, self.guide_rounds
        if isinstance(n, bool) or not isinstance(n, int) or n < 0 or n == 1:
            raise ValueError(f"--guide-orbits must be 0 (none) or an integer at least 2, "
                             f"not {n!r}")
        if isinstance(w, bool) or not isinstance(w, (int, float)) or not (
                math.isfinite(w) and w > 0):
            raise ValueError(f"--guide-weight must be a number above 0, not {w!r}")
        if r is None:
            r = DEFAULT_GUIDE_ROUNDS if self._guide_rounds_apply() else 0
            object.__setattr__(self, "guide_rounds", r)
        if isinstance(r, bool) or not isinstance(r, int) or r < 0:
            raise ValueError(f"--guide-rounds must be an integer at least 0, not {r!r}")
        if n and r:
            raise ValueError("--guide-orbits and --guide-rounds do not combine (guides in "
                             "every start's training, or in rounds for the starts that "
                             "break the picture)")
        flag = "--guide-orbits" if n else "--guide-rounds" if r else None
        if flag is None:
            return
        if not system_kind(self.system).autonomous:
            raise ValueError(f"{flag} applies to --system flutter only (the curve is "
                             "a self-excited branch's, from a Hopf point through one fold)")
        if self.approximator != "nn" or self.training != "periodic":
            raise ValueError(f"{flag} applies to --approximator nn --training periodic "
                             "only (a guide is an orbit of the periodic loss)")
        for other, on in (("--amplitude-stages", self.train.amplitude_stages),
                          ("--branch-rounds", self.train.branch_rounds),
                          ("--monotone-rounds", self.train.monotone_rounds)):
            if on:
                raise ValueError(f"{flag} and {other} do not combine ({other} plans "
                                 "from the measured orbits alone)")

    def _guide_rounds_apply(self) -> bool:
        """Whether the default guide rounds apply: the aerofoil's network with periodic
        training, without guides in every start or the experimental plans from the measured
        orbits alone."""
        t = self.train
        return (system_kind(self.system).autonomous and self.approximator == "nn"
                and self.training == "periodic" and t.form == "network"
                and not self.guide_orbits and not t.amplitude_stages
                and not t.branch_rounds and not t.monotone_rounds)

    def _defaults_that_apply(self) -> TrainConfig:
        """The training configuration with the aerofoil's defaults (fields left at None)
        switched off where they do not apply: the rest-free network needs the network (not
        the GP, not the amplitude form); the constraint rounds need it too, periodic
        training and the starts trained one at a time; the start from the mechanistic model,
        the backbone's margins and collocation, the network on a self-excited system's
        periodic orbits.
        (An explicit request where one does not apply was refused above.)"""
        t = self.train
        network = self.approximator == "nn" and t.form == "network"
        if t.rest_free is None and not network:
            t = dataclasses.replace(t, rest_free=False)
        if t.constraint_rounds is None and not (network and self.training == "periodic"
                                                and not self.starts_together):
            t = dataclasses.replace(t, constraint_rounds=0)
        # the aerofoil's network on periodic orbits starts from the mechanistic model, with
        # the data's margins: without the residual-force fit no start bends its branch into
        # an S, and the margins hold each labelled orbit's stability as far from neutral as
        # the points support, where the one-period closure alone barely sees an orbit go
        # (docs/fitting.md)
        on = (network and self.training == "periodic"
              and system_kind(self.system).autonomous)
        # and its long first training runs on the collocated orbits, where a step costs a
        # sixth of shooting's: the shooting steps after it finish on the same objective
        for name in ("from_mechanistic", "backbone_margins", "collocation"):
            if getattr(t, name) is None:
                t = dataclasses.replace(t, **{name: on})
        return t

    def reference(self) -> dict:
        """The known Hopf and fold airspeeds given, as {"hopf": V, "fold": V}."""
        return {k: v for k, v in (("hopf", self.reference_hopf),
                                  ("fold", self.reference_fold)) if v is not None}

    def control(self) -> ControlChoice | None:
        """The recorded control as a known input, as asked (None: the fit takes the
        orbits as open-loop ones)."""
        return ControlChoice.of(self.system, self.control_input, self.control_gain)

    def to_json(self) -> dict:
        d = asdict(self)
        d["train"] = self.train.for_system(self.system).to_json()   # the values actually used
        return d


