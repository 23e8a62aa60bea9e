"""Campaign fleets on Ray: a grid of campaign files x rig settings x seeds, each member a Ray
task running `cbc-campaign run` with its own embedded rig on its node's loopback.

    options = load_fleet("fleet.toml")      # typed, checked: FleetError names the field
    status = run_fleet(options, "out/")     # RAY_ADDRESS, or a local Ray

Ray is the optional extra ``cluster``; nothing here imports it until a fleet runs.
"""

from .driver import FleetIndex, connect, run_fleet
from .member import MemberResult, run_member
from .options import FleetError, FleetOptions, Member, RigSettings, load_fleet, parse_fleet

__all__ = ["FleetError", "FleetIndex", "FleetOptions", "Member", "MemberResult", "RigSettings",
           "connect", "load_fleet", "parse_fleet", "run_fleet", "run_member"]
