"""Regenerate docs/examples/loop_heave_cubic/: a campaign on an aerofoil rig started with
an undeclared cubic heave spring (--effect heave_cubic=5e5, sigma 0.02, seed 0; the rig's
own true orbits held by its board, 4 s raw records each), and `ude-fit loop` on it. The
campaign (7.6 MB) is written to a temporary folder and not kept; the report records its
SHA-256, and this script remakes it bit for bit.

    python3 docs/make_loop_example.py
"""

import os
import sys
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, ".."))

from tests.ude_fixtures import write_truth_campaign  # noqa: E402
from ude_fit import cli  # noqa: E402

out = os.path.join(HERE, "examples", "loop_heave_cubic")
os.makedirs(out, exist_ok=True)
with tempfile.TemporaryDirectory() as tmp:
    data = os.path.join(tmp, "heave_cubic_campaign.h5")
    write_truth_campaign(data, "flutter", sigma=0.02, seed=0, effects=("heave_cubic=5e5",))
    os.chdir(os.path.join(HERE, ".."))
    rc = cli.main(["loop", data, "--system", "flutter", "--out", os.path.relpath(out),
                   "--quiet"])
sys.exit(rc)
