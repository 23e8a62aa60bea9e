"""CBC methods as plans: generators of engine messages (see messages.py).

Each plan takes its typed options (`options.py`, built from the campaign's ``[cbc]`` table),
shares its common steps with the others (`_steps.py`) and never imports the engine."""

from .autonomous import flutter_plan
from .forced import oscillator_plan
from .options import FlutterOptions, ForcedOptions, PlanOptions, plan_options


def plan_for(config: dict):
    """The plan a validated campaign config asks for."""
    if config["campaign"]["rig"] == "flutter":
        return flutter_plan(config)
    return oscillator_plan(config)


__all__ = ["FlutterOptions", "ForcedOptions", "PlanOptions", "flutter_plan", "oscillator_plan",
           "plan_for", "plan_options"]
