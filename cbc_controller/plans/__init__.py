"""CBC methods as plans: generators of engine messages (see messages.py)."""

from .autonomous import flutter_plan
from .forced import oscillator_plan


def plan_for(config: dict):
    """The plan a validated campaign config asks for."""
    if config["campaign"]["rig"] == "flutter":
        return flutter_plan(config)
    return oscillator_plan(config)


__all__ = ["flutter_plan", "oscillator_plan", "plan_for"]
