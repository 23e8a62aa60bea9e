"""The command line over the library: ``ude-fit pipeline`` takes every option ``ude-fit
fit`` takes and hands the library the same options object; bad input is rejected before
anything is written; folders of campaign files load; the library refuses float32."""

from __future__ import annotations

import subprocess
import sys
import tempfile
from pathlib import Path

import jax
import pytest

from tests.ude_fixtures import write_truth_campaign
from ude_fit import EnergyRising, FitOptions, OrbitDataset, load
from ude_fit.training.options import TrainConfig
from ude_fit.cli import build_parser
from ude_fit.cli import main as cli_main
from ude_fit.cli import common as cli_common
from ude_fit.cli import pipeline as pipeline_cli
from ude_fit.cli.options import fit_options

jax.config.update("jax_enable_x64", True)       # ude_fit computes in float64 (see ude_fit docs)

# a parameter file for --mechanistic-params (read when the options are built)
PARAMS_TOML = Path(tempfile.mkdtemp(prefix="ude_cli_")) / "rig.toml"
PARAMS_TOML.write_text("k_h = 3300.0\n")

# every fit option at a value other than its default (the NN approximator's, and the GP's)
NN_FLAGS = ["--mechanistic-params", str(PARAMS_TOML), "--training", "trajectory", "--mechanistic", "periodic", "--starts", "3",
            "--seed", "7", "--width", "9", "--depth", "3", "--energy-shape", "1.5",
            "--energy-rising", "2.5", "--rest-stability", "3.5", "--unstable-branch", "7.5",
            "--equilibrium-penalty", "4.5", "--smoothness-penalty", "5.5",
            "--weight-decay", "6.5", "--param-scale", "2", "--param-dependence", "polynomial",
            "--param-degree", "3", "--reference-hopf", "24.1", "--reference-fold", "20.4",
            "--no-rest-free", "--starts-together", "--from-mechanistic"]
# the amplitude form of the correction (no network options with it), the constraint, branch
# and monotone rounds and the amplitude stages (which --training trajectory above excludes)
FORM_FLAGS = ["--correction-form", "amplitude", "--seed", "5", "--constraint-rounds", "2",
              "--constrain-unstable-branch", "--parameter-errors", "--branch-rounds", "3",
              "--monotone-rounds", "4", "--amplitude-stages", "--stability-margin", "0.05",
              "--backbone-margins"]
GP_FLAGS = ["--approximator", "gp", "--starts", "2", "--seed", "3", "--reference-hopf", "24.1"]
# the guide orbits (periodic training of the network, without the rounds above), with
# collocation's series solved for the model and the sensors' zero identified
GUIDE_FLAGS = ["--guide-orbits", "10", "--guide-weight", "0.5", "--seed", "4",
               "--collocation-series", "solved", "--sensor-zero", "identified"]
# the guide rounds (on by default; another count, and the first round's weight), and the
# first training by shooting instead of collocation
ROUND_FLAGS = ["--guide-rounds", "3", "--guide-weight", "0.2", "--seed", "6",
               "--no-collocation"]
# fit options the pipeline refuses (tests/test_ude_control_input.py checks the refusal)
FIT_ONLY_FLAGS = ["--control-input", "--control-gain", "2.5",
                  "--add", "heave_unsteady_aero", "pitch_freeplay=0.01"]


def _fit_dests() -> set[str]:
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    return {a.dest for a in sub.choices["fit"]._actions} - {"help", "out", "quiet"}


@pytest.mark.parametrize("flags", [NN_FLAGS, FORM_FLAGS, GP_FLAGS, GUIDE_FLAGS, ROUND_FLAGS])
def test_pipeline_builds_the_options_fit_builds(flags):
    parser = build_parser()
    common = ["data.h5", "--system", "flutter", *flags, "--out", "o"]
    fit_args = parser.parse_args(["fit", *common])
    pipe_args = parser.parse_args(["pipeline", *common])
    opts = fit_options(fit_args)
    assert pipeline_cli.pipeline_options(pipe_args).fit == opts
    assert opts != FitOptions("flutter")


def test_every_fit_flag_is_set_by_the_test_and_taken_by_the_pipeline():
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    pipe = {a.dest for a in sub.choices["pipeline"]._actions}
    assert _fit_dests() <= pipe
    flags = {f.lstrip("-").removeprefix("no-").replace("-", "_")
             for f in NN_FLAGS + FORM_FLAGS + GP_FLAGS + GUIDE_FLAGS + ROUND_FLAGS
             + FIT_ONLY_FLAGS
             if f.startswith("--")}
    assert _fit_dests() - {"data", "system", "stability"} == flags


def test_the_fit_takes_its_own_flags():
    args = build_parser().parse_args(["fit", "data.h5", "--system", "flutter",
                                      *FIT_ONLY_FLAGS, "--out", "o"])
    opts = fit_options(args)
    assert opts.control_input and opts.control_gain == 2.5
    assert opts == FitOptions("flutter", control_input=True, control_gain=2.5,
                              mechanistic_effects=(("heave_unsteady_aero", None),
                                                   ("pitch_freeplay", 0.01)))


def test_the_stability_margin_reaches_the_training(capsys):
    parse = lambda *f: fit_options(build_parser().parse_args(
        ["fit", "data.h5", "--system", "flutter", *f, "--out", "o"]))
    assert parse("--stability-margin", "0.08").train.stability_margin == 0.08
    assert parse().train.stability_margin == TrainConfig().stability_margin
    for bad in ("0", "-0.1", "nan"):
        with pytest.raises(SystemExit) as exit_:
            parse("--stability-margin", bad)
        assert exit_.value.code == 2
        assert "--stability-margin must be" in capsys.readouterr().err


def test_backbone_margins_reach_the_training_of_a_self_excited_system(tmp_path, capsys):
    parse = lambda *f: fit_options(build_parser().parse_args(
        ["fit", "data.h5", *f, "--out", "o"]))
    # on by default where they apply, off where asked or where they do not apply
    assert parse("--system", "flutter").train.backbone_margins is True
    assert parse("--system", "flutter", "--no-backbone-margins").train.backbone_margins is False
    for where in (["--system", "oscillator"], ["--system", "flutter", "--approximator", "gp"],
                  ["--system", "flutter", "--training", "trajectory"]):
        assert parse(*where).train.backbone_margins is False, where
    for argv, message in [(["--system", "oscillator"], "--backbone-margins applies to "
                           "--system flutter with --training periodic only"),
                          (["--system", "flutter", "--approximator", "gp"],
                           "--backbone-margins apply to --approximator nn only")]:
        out = tmp_path / "out"
        rc = cli_main(["fit", "data.h5", *argv, "--backbone-margins", "--out", str(out),
                       "--quiet"])
        err = capsys.readouterr().err
        assert rc == 2 and message in err and len(err.strip().splitlines()) == 1, err
        assert not out.exists()


def test_a_start_from_the_mechanistic_model_is_a_network_option(tmp_path, capsys):
    parse = lambda *f: fit_options(build_parser().parse_args(
        ["fit", "data.h5", "--system", "flutter", *f, "--out", "o"]))
    assert parse().train.from_mechanistic is True
    assert parse("--no-from-mechanistic").train.from_mechanistic is False
    # explicitly asked of trajectory training it applies; by default only to periodic orbits
    assert parse("--training", "trajectory").train.from_mechanistic is False
    assert parse("--training", "trajectory", "--from-mechanistic").train.from_mechanistic
    assert parse("--approximator", "gp").train.from_mechanistic is False
    out = tmp_path / "out"
    rc = cli_main(["fit", "data.h5", "--system", "flutter", "--approximator", "gp",
                   "--from-mechanistic", "--out", str(out), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2 and "--from-mechanistic" in err and "--approximator nn only" in err, err
    assert len(err.strip().splitlines()) == 1 and not out.exists()


@pytest.mark.parametrize("argv, message", [
    (["fit", "--add", "wake"], "unknown effect 'wake' for the flutter model"),
    (["fit", "--add", "heave_unsteady_aero=0.1"],
     "--add heave_unsteady_aero=0.1: heave_unsteady_aero has no shape parameter"),
    (["fit", "--add", "pitch_freeplay=0"], "--add pitch_freeplay=0: the delta (rad) must be "
     "positive"),
    (["fit", "--add", "heave_cubic", "heave_cubic"], "--add heave_cubic given twice"),
    (["fit", "--add", "pitch_freeplay"], "--add pitch_freeplay: give its delta (rad) "
     "(pitch_freeplay=VALUE)"),
    (["fit", "--add", "heave_cubic", "--approximator", "gp"],
     "--add apply to --approximator nn only"),
    (["pipeline", "--add", "heave_cubic"], "--add applies to ude-fit fit only"),
])
def test_effects_to_add_are_checked(tmp_path, capsys, argv, message):
    """``--add``: every mistake is one line naming it, exit 2, nothing written."""
    out = tmp_path / "out"
    rc = cli_main([argv[0], "data.h5", "--system", "flutter", *argv[1:], "--out", str(out),
                   "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2 and message in err and len(err.strip().splitlines()) == 1, err
    assert not out.exists()


def test_pipeline_hands_the_library_the_options(monkeypatch, tmp_path):
    """Through the command itself: the options object that reaches run_pipeline."""
    seen = {}

    class Reached(Exception):
        pass

    def run_pipeline(ds, options, progress=None):
        seen["options"] = options
        raise Reached

    monkeypatch.setattr(cli_common, "load", lambda paths, system, stability=None:
                        OrbitDataset(system, (), ()))
    monkeypatch.setattr(pipeline_cli, "run_pipeline", run_pipeline)
    argv = ["pipeline", "data.h5", "--system", "flutter", *NN_FLAGS, "--max-effects", "2",
            "--out", str(tmp_path / "o"), "--quiet"]
    args = build_parser().parse_args(argv)
    with pytest.raises(Reached):
        pipeline_cli.run(args, argv)
    expected = fit_options(build_parser().parse_args(
        ["fit", "data.h5", "--system", "flutter", *NN_FLAGS, "--out", "o"]))
    assert seen["options"].fit == expected and seen["options"].max_effects == 2
    assert seen["options"].fit.train.penalty(EnergyRising) == EnergyRising(2.5)


def _run(*args):
    return subprocess.run([sys.executable, "-m", "ude_fit.cli", *args], capture_output=True,
                          text=True, timeout=120)


@pytest.mark.parametrize("command", ["fit", "pipeline"])
def test_bad_input_writes_nothing(tmp_path, command):
    bad = tmp_path / "notes.h5"
    bad.write_text("not hdf5")
    (tmp_path / "empty").mkdir()
    for data, words in ((bad, ("notes.h5",)), (tmp_path / "empty", (".h5", ".mat"))):
        out = tmp_path / f"out_{data.name}"
        r = _run(command, str(data), "--system", "flutter", "--out", str(out))
        assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
        assert all(w in r.stderr for w in words), r.stderr
        assert not out.exists()


def test_a_folder_of_campaign_files_loads_as_its_files(tmp_path):
    folder = tmp_path / "campaigns"
    folder.mkdir()
    write_truth_campaign(folder / "a.h5", "flutter", airspeeds=(18.0, 21.0))
    write_truth_campaign(folder / "b.h5", "flutter", airspeeds=(23.6,))
    ds = load(folder, "flutter")
    both = load([folder / "a.h5", folder / "b.h5"], "flutter")
    assert len(ds) == len(both) == 6          # two orbits at each airspeed
    assert [o.parameter for o in ds] == [o.parameter for o in both]


def test_the_library_refuses_to_fit_in_float32():
    code = ("import ude_fit\n"
            "try:\n"
            "    ude_fit.fit(None, ude_fit.FitOptions('flutter'))\n"
            "except RuntimeError as e:\n"
            "    assert 'float64' in str(e)\n"
            "else:\n"
            "    raise SystemExit('no error')\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stderr
