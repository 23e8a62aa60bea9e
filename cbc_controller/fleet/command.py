"""`cbc-campaign fleet FLEET.toml --out DIR [--address ADDR]`: the fleet subcommand."""

from __future__ import annotations

import sys


def add_fleet_parser(sub) -> None:
    f = sub.add_parser("fleet", help="run a grid of campaigns (campaign files x rig settings x "
                       "seeds) as Ray tasks; a rerun skips what is done")
    f.add_argument("fleet", metavar="FLEET.toml", help="the fleet file (see docs/cluster.md)")
    f.add_argument("--out", required=True, metavar="DIR",
                   help="output folder: index.json, index.md, members/<id>/campaign.h5")
    f.add_argument("--address", metavar="ADDR",
                   help="the Ray cluster to join (default: $RAY_ADDRESS; with neither, a local "
                        "Ray on this machine)")
    f.add_argument("--check", action="store_true",
                   help="check the fleet file and list its members; run nothing")


def run_fleet_command(args) -> int:
    from .driver import ClusterError, run_fleet
    from .options import FleetError, load_fleet
    try:
        options = load_fleet(args.fleet)
        if args.check:
            for m in options.members():
                print(m.id)
            return 0
        return run_fleet(options, args.out, args.address)
    except (FleetError, ClusterError) as exc:
        print(f"cbc-campaign: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
