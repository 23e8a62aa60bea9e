"""What every subcommand shares: the one-line usage error, terminal progress, the output
folder, and the command line as written into the results."""

from __future__ import annotations

import argparse
import os
import shlex
import sys
import time

from ..data import load
from ..report.format import pct

EXIT_USAGE = 2


class Parser(argparse.ArgumentParser):
    def error(self, message):          # one line, exit 2
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message}\n")


class UsageError(Exception):
    """A user's mistake: printed as one line, exit status 2."""


def command_line(argv) -> str:
    return "ude-fit " + " ".join(shlex.quote(a) for a in argv)


def out_dir(path: str) -> str:
    """The output folder, created; call it once the inputs have been checked."""
    if os.path.exists(path) and not os.path.isdir(path):
        raise UsageError(f"--out {path}: exists and is not a folder")
    try:
        os.makedirs(path, exist_ok=True)
    except OSError as exc:
        raise UsageError(f"--out {path}: cannot create ({exc.strerror})") from None
    return path


def start(args, build_options, fit_of=lambda opts: opts):
    """What a fitting command does first, in this order so that nothing is written for bad
    input: its options (a ValueError becomes the usage error), the data about the sensors'
    zero the fit's options (``fit_of(options)``) ask for, the output folder, the progress
    display. Returns (options, dataset, folder, progress)."""
    try:
        opts = build_options(args)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    from ..mechanistic_stage import with_chosen_zero
    ds = with_chosen_zero(load_data(args), fit_of(opts))
    return opts, ds, out_dir(args.out), Progress(args.quiet)


def load_data(args):
    """The dataset DATA... and --system (and --stability) ask for, each point about its own
    mean where its file does not record the sensors' zero (training.sensor_zero)."""
    from ..data import StabilityLabels
    try:
        labels = StabilityLabels.parse(args.stability)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    return load(args.data, args.system, labels)


class Progress:
    """Terminal progress: stages, and training loss/step/elapsed at most every 2 s."""

    def __init__(self, quiet: bool):
        self.quiet = quiet
        self.t0 = time.perf_counter()
        self.last = 0.0

    def say(self, text):
        if not self.quiet:
            print(f"[{time.perf_counter() - self.t0:7.1f} s] {text}", file=sys.stderr, flush=True)

    def __call__(self, event, **kw):
        if event == "stage":
            self.say(kw["stage"])
        elif event == "model":
            m = kw["metrics"].summary
            self.say(f"{kw['which']} model: branch RMS {pct(m.branch_rms)}, missed "
                     f"{m.missed}")
        elif event == "start":
            self.say(f"start {kw['start']}/{kw['starts']}")
        elif event == "train":
            now = time.perf_counter()
            if now - self.last >= 2.0 or kw.get("step") == kw.get("steps"):
                self.last = now
                if "lanes" in kw:            # the starts trained together: the best loss
                    who, loss = f"{kw['lanes']} starts", f"best loss {kw['loss']:.3e}"
                else:
                    who = f"start {kw['start']}" if kw["start"] else "identification"
                    loss = f"loss {kw['loss']:.3e}"
                self.say(f"  {who} {kw['stage']} {kw['optimiser']} step "
                         f"{kw['step']}/{kw['steps']} {loss} ({kw['elapsed']:.1f} s)")
        elif event == "step":
            r = kw["record"]
            self.say(f"step {r['step']}: {r.get('name') or r.get('candidate')} "
                     f"{'kept' if r['kept'] else 'not kept'} ({r['reason']})")
        elif event == "start_done":
            r = kw["record"]
            if r.ok:
                self.say(f"start {r.start} done in {r.seconds:.1f} s: branch RMS "
                         f"{pct(r.metrics.summary.branch_rms)}, missed "
                         f"{r.metrics.summary.missed}")
            else:
                self.say(f"start {r.start} dropped: {r.reason}")
