"""The command line's argument types and the one argument group every fitting command
shares (``ude-fit fit`` and ``ude-fit pipeline``), turned into one :class:`FitOptions`.

Argument types only parse (an integer, a finite number, a sign); what a value means for
a fit (which penalties suit which system and approximator, ...) is checked once, by
:class:`FitOptions` itself, whose ValueError the command line prints as its one-line
usage error.
"""

from __future__ import annotations

import argparse

SYSTEMS = ("flutter", "oscillator")


def positive_int(name, least: int = 1):
    def conv(s):
        try:
            v = int(s)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name} must be an integer, not {s!r}") from None
        if v < least:
            raise argparse.ArgumentTypeError(f"{name} must be at least {least}, not {v}")
        return v
    return conv


def finite_float(name):
    def conv(s):
        try:
            v = float(s)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name} must be a number, not {s!r}") from None
        if v != v or v in (float("inf"), float("-inf")):
            raise argparse.ArgumentTypeError(f"{name} must be finite, not {s!r}")
        return v
    return conv


def _bounded_float(name, ok, must: str):
    finite = finite_float(name)

    def conv(s):
        v = finite(s)
        if not ok(v):
            raise argparse.ArgumentTypeError(f"{name} must {must}, not {s!r}")
        return v
    return conv


def nonnegative_float(name):
    return _bounded_float(name, lambda v: v >= 0, "not be negative")


def positive_float(name):
    return _bounded_float(name, lambda v: v > 0, "be positive")


def add_data_arguments(p) -> None:
    """DATA... and --system, which every command that reads measurements takes."""
    p.add_argument("data", nargs="+", metavar="DATA",
                   help="campaign HDF5 files, lee2020 .mat files, or folders of them")
    p.add_argument("--system", required=True, choices=SYSTEMS)
    p.add_argument("--stability", action="append", default=[], metavar="GLOB=LABEL",
                   help="stability of the points whose file name matches GLOB (shell "
                   "pattern; a campaign point also matches as NAME.h5#KEY): stable or "
                   "unstable; several rules comma-separated or the flag repeated. Wins over "
                   "the file names (CBC_stable_*, CBC_unstable_*, CBC_v*) and the campaign's "
                   "own labels; a rule that matches no point is an error")


def add_sensor_zero_argument(p) -> None:
    """--sensor-zero, which every command that identifies a mechanistic model takes."""
    from ..training.sensor_zero import AUTO, SENSOR_ZERO_CHOICES
    p.add_argument("--sensor-zero", default=AUTO, choices=SENSOR_ZERO_CHOICES,
                   help="where the points' rest position comes from when their files do not "
                   "record it (wind-tunnel .mat files): each point's own mean (own-means), "
                   "identified from all points with the mechanistic model and the zero-lift "
                   "incidence whose lift moves it with the airspeed (identified), or "
                   "(auto, the default) the identified one where the mechanistic model "
                   "identified with it meets the measured diagram better (fewer points "
                   "missed, then a smaller branch error)")


def add_fit_arguments(p) -> None:
    """Every option of a fit (:class:`FitOptions`): the same flags, the same defaults, for
    every command that fits."""
    from ..training.options import COLLOCATION_SERIES, DEFAULT_STARTS
    from ..training.penalties import PENALTIES

    p.add_argument("--approximator", default="nn", choices=("nn", "gp"),
                   help="the correction: a neural network (default) or a Gaussian process")
    p.add_argument("--training", default="periodic", choices=("trajectory", "periodic"),
                   help="NN loss: one-period trajectories from the measured states (the "
                   "paper's) or closed periodic orbits with stability labels (default)")
    p.add_argument("--mechanistic", default="equation", choices=("equation", "periodic"),
                   help="mechanistic identification: least squares on the equation error "
                   "(default), or that refined by output error on the periodic orbits")
    p.add_argument("--starts", type=positive_int("--starts"), default=DEFAULT_STARTS,
                   help="random starts; an adequate one is kept, the medoid of 3 or more "
                        f"with the fewest folds (default {DEFAULT_STARTS})")
    p.add_argument("--starts-together", action="store_true",
                   help="train the network's starts together: Adam vmapped over the starts, "
                   "L-BFGS one start at a time (each start the same as alone; 16 starts "
                   "measured 1.3x faster than one after another on 2 cores, see "
                   "docs/benchmarks.md)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    add_sensor_zero_argument(p)
    p.add_argument("--width", type=positive_int("--width"), default=12,
                   help="hidden units per layer of the NN (default 12)")
    p.add_argument("--depth", type=positive_int("--depth"), default=2,
                   help="hidden layers of the NN (default 2)")
    for kind in PENALTIES:
        flag = f"--{kind.option}"
        p.add_argument(flag, type=nonnegative_float(flag), default=0.0, metavar="W",
                       help=kind.help)
    p.add_argument("--param-scale", type=positive_float("--param-scale"), default=1.0,
                   metavar="F", help="the network's parameter input is standardised by F times "
                   "its spread in the data; larger F, slower variation with it (default 1)")
    p.add_argument("--param-dependence", default="input", choices=("input", "polynomial"),
                   help="how the NN correction depends on the bifurcation parameter: as an "
                   "input like the states (default), or as a polynomial in it "
                   "(--param-degree) with state-dependent coefficients, which cannot wiggle "
                   "in it (the airspeed enters quasi-steady aerodynamics as V and V^2)")
    p.add_argument("--param-degree", type=positive_int("--param-degree", 0),
                   default=2, metavar="D", help="--param-dependence polynomial: the degree "
                   "(default 2; 0: a correction of the states alone)")
    p.add_argument("--rest-free", action=argparse.BooleanOptionalAction, default=None,
                   help="aerofoil: the network's value and slope at rest are subtracted, so "
                   "it cannot move the equilibrium or its linearisation; explicit linear "
                   "terms on the displacements and velocities, affine in the airspeed, carry "
                   "the linear change (where the Hopf point lies). Default: on for the "
                   "aerofoil's network (--no-rest-free: the plain network)")
    p.add_argument("--correction-form", default="network", choices=("network", "amplitude"),
                   help="the correction's form: a neural network of the states and the "
                   "parameter (default), or (experimental, aerofoil) linear terms plus a "
                   "damping convex in the oscillation's size, the Hopf point held where the "
                   "unstable orbits point (docs/fitting.md; not a default)")
    p.add_argument("--constraint-rounds", type=positive_int("--constraint-rounds", 0),
                   default=None, metavar="N",
                   help="aerofoil, periodic training: where the trained model breaks the "
                   "energy-rising or rest-stability condition, train on with that penalty "
                   "weighted to count as much as the data's misfit, ten times more each "
                   "round while it is still broken, at most N rounds; a model that meets "
                   "both is left as it is; no weights to choose (docs/fitting.md; default 7 "
                   "for the aerofoil's network trained on periodic orbits one start at a "
                   "time, else 0)")
    p.add_argument("--constrain-unstable-branch", action="store_true",
                   help="aerofoil, experimental: the constraint rounds hold the "
                   "unstable-branch condition too (the model's branch, followed in amplitude "
                   "from its Hopf point by one-harmonic balance, falls in airspeed all along "
                   "the unstable stretch the data shows: no supercritical Hopf point and no "
                   "S-bend between the unstable orbits; docs/fitting.md; off by default)")
    p.add_argument("--stability-margin", type=positive_float("--stability-margin"),
                   default=None, metavar="M",
                   help="periodic training: how far beyond neutral a labelled orbit's "
                   "stability indicator must lie on its labelled side before the stability "
                   "term lets it be; for the aerofoil's orbits labelled stable, their "
                   "period-doubling and torus tests too (default: the training's, in "
                   "docs/fitting.md; "
                   "benchmarks/label_margins.py shows how firmly a fit's starts hold each "
                   "label; experimental)")
    p.add_argument("--backbone-margins", action=argparse.BooleanOptionalAction, default=None,
                   help="aerofoil, periodic training: each labelled orbit's stability margin "
                   "as the points' Hopf normal-form backbone and its branch's straight line "
                   "predict it (the smaller, one standard error towards neutral; none for the "
                   "orbits next to the fold), never below --stability-margin. Default: on for "
                   "the aerofoil's network (--no-backbone-margins: --stability-margin for "
                   "every orbit; docs/fitting.md)")
    p.add_argument("--from-mechanistic", action=argparse.BooleanOptionalAction, default=None,
                   help="network: no equation stage; each start's first training begins at "
                   "the mechanistic model and takes the longer step counts it needs to learn "
                   "the whole correction. Default: on for the aerofoil's network on periodic "
                   "orbits (--no-from-mechanistic: the fit to the residual forces first; "
                   "docs/fitting.md)")
    p.add_argument("--collocation", action=argparse.BooleanOptionalAction, default=None,
                   help="periodic training: each start's first (long) training with every "
                   "orbit collocated, a free Fourier series the model's vector field must "
                   "follow, instead of integrated; the periodic stage's shooting steps "
                   "finish it (docs/fitting.md)")
    p.add_argument("--collocation-series", choices=COLLOCATION_SERIES, default=None,
                   help="with --collocation: where the orbits' series come from; free, "
                   "unknowns of the optimiser beside the model; solved for the model at "
                   "every step (variable projection: about twice the cost of a step, and no "
                   "lag of the series behind the network on noisy orbits); or free for the "
                   "first Adam steps, solved after them (free-then-solved, the "
                   "default; docs/fitting.md)")
    p.add_argument("--parameter-errors", action="store_true",
                   help="aerofoil, periodic training, experimental: every orbit's airspeed "
                   "is an unknown too, off its measured value at a cost set by the data's own "
                   "scatter about smooth branches, read in amplitude and in airspeed "
                   "(orthogonal regression; docs/fitting.md; off by default)")
    p.add_argument("--branch-rounds", type=positive_int("--branch-rounds", 0),
                   default=0, metavar="N",
                   help="aerofoil, periodic training: N rounds of training on with the "
                   "measured orbits asked to lie on the branch from the Hopf point, traced "
                   "in amplitude, with the slope their stability implies and one turn at "
                   "most (docs/fitting.md; default 0)")
    p.add_argument("--monotone-rounds", type=positive_int("--monotone-rounds", 0),
                   default=0, metavar="N",
                   help="aerofoil, periodic training (experimental): N rounds of training on "
                   "with the model's branch asked to be monotone between measured orbits of "
                   "the same stability (falling where unstable, rising where stable) and to "
                   "keep rising above the largest stable orbit, traced from the fitted orbits "
                   "in amplitude; weighted from the data's misfit (docs/fitting.md; default 0)")
    p.add_argument("--amplitude-stages", action="store_true",
                   help="aerofoil, periodic training: train on the orbit nearest the Hopf "
                   "point first, then add the orbits one at a time in the order a branch "
                   "with one fold meets them (unstable, then stable, each by airspeed), "
                   "before the stage on all of them (experimental; docs/fitting.md)")
    p.add_argument("--guide-orbits", type=positive_int("--guide-orbits", 0), default=0,
                   metavar="N",
                   help="aerofoil, periodic training (experimental): fit a curve with one "
                   "Hopf point and one fold to the points, and train on N of its orbits as "
                   "well, evenly spaced in amplitude from the smallest orbit's to 15 %% above "
                   "the largest orbit, their heave only, each at --guide-weight "
                   "(docs/fitting.md; default 0: none)")
    p.add_argument("--guide-weight", type=positive_float("--guide-weight"), default=0.3,
                   metavar="W", help="--guide-orbits, --guide-rounds: each guide's weight "
                   "against a measured orbit's 1 (the first round's; default 0.3)")
    p.add_argument("--guide-rounds", type=positive_int("--guide-rounds", 0), default=None,
                   metavar="R",
                   help="aerofoil, the network with periodic training: a start whose traced "
                   "diagram has more folds than the adequacy rule allows, or misses a measured "
                   "point, is trained on with orbits of a one-fold curve fitted to the points, "
                   "where no measured orbit is near, over the whole amplitude window, for up "
                   "to R rounds, each at three times the last round's weight; it keeps the "
                   "model nearest the rule that misses no more points (docs/fitting.md; "
                   "default 2 where it applies, 0 turns it off)")
    add_control_arguments(p)
    p.add_argument("--add", nargs="+", default=[], metavar="EFFECT[=SHAPE]",
                   help="library effects to add to the mechanistic model as terms of their "
                   "own, identified with it (see `ude-fit explain`; e.g. the aerofoil's "
                   "heave_unsteady_aero pitch_unsteady_aero, the wake's lag); an effect "
                   "with a shape (a freeplay gap, a lag time constant) needs it as =SHAPE "
                   "(ude-fit refine chooses it by cross-validation)")
    p.add_argument("--mechanistic-params", metavar="FILE.toml",
                   help="the mechanistic model's values you know (TOML, name = number): "
                   "geometry replaces the design values, damping/stiffness given are not "
                   "identified; the report says where every parameter came from")
    p.add_argument("--reference-hopf", type=finite_float("--reference-hopf"), metavar="V",
                   help="known Hopf airspeed (m/s) for the error figures")
    p.add_argument("--reference-fold", type=finite_float("--reference-fold"), metavar="V",
                   help="known fold airspeed (m/s) for the error figures")


def add_control_arguments(p) -> None:
    """--control-input and --control-gain (fit, pipeline, explain, refine, loop)."""
    p.add_argument("--control-input", action="store_true",
                   help="aerofoil: the recorded holding control as a known force on heave, "
                   "so a point held with some control is fitted as an orbit of the "
                   "controlled system; the diagram is the open-loop one")
    p.add_argument("--control-gain", type=finite_float("--control-gain"), metavar="G",
                   help="--control-input: newtons per unit of the recorded control (default: "
                   "1 for a control recorded in N, else identified with the mechanistic "
                   "parameters)")


def control_choice(args):
    """The :class:`ControlChoice` the flags of :func:`add_control_arguments` ask for (None
    without --control-input); ValueError naming the option otherwise."""
    from ..training.control import ControlChoice
    return ControlChoice.of(args.system, args.control_input, args.control_gain)


def fit_options(args):
    """The :class:`FitOptions` the flags of :func:`add_fit_arguments` (and --system) ask
    for; ValueError (naming the option) if they do not make one."""
    from ..training.options import FitOptions
    from ..training.penalties import PENALTIES
    from ..training.options import TrainConfig

    from ..models.parameter_file import MechanisticParameters

    penalties = tuple(kind(getattr(args, kind.option.replace("-", "_"))) for kind in PENALTIES)
    params = (None if args.mechanistic_params is None else
              MechanisticParameters.read(args.mechanistic_params, args.system))
    from ..models.library import parse_effects
    return FitOptions(
        mechanistic_parameters=params,
        mechanistic_effects=parse_effects(args.system, args.add),
        system=args.system, approximator=args.approximator, training=args.training,
        starts=args.starts, starts_together=args.starts_together, seed=args.seed,
        mechanistic=args.mechanistic,
        control_input=args.control_input, control_gain=args.control_gain,
        guide_orbits=args.guide_orbits, guide_weight=args.guide_weight,
        guide_rounds=args.guide_rounds, sensor_zero=args.sensor_zero,
        reference_hopf=args.reference_hopf, reference_fold=args.reference_fold,
        train=TrainConfig(width=args.width, depth=args.depth, param_scale=args.param_scale,
                          param_dependence=args.param_dependence,
                          param_degree=args.param_degree, rest_free=args.rest_free,
                          form=args.correction_form,
                          constraint_rounds=args.constraint_rounds,
                          constrain_unstable_branch=args.constrain_unstable_branch,
                          parameter_errors=args.parameter_errors,
                          backbone_margins=args.backbone_margins,
                          from_mechanistic=args.from_mechanistic,
                          collocation=args.collocation,
                          collocation_series=args.collocation_series,
                          **({} if args.stability_margin is None
                             else {"stability_margin": args.stability_margin}),
                          branch_rounds=args.branch_rounds,
                          monotone_rounds=args.monotone_rounds,
                          amplitude_stages=args.amplitude_stages,
                          penalties=tuple(p for p in penalties if p.weight)))
