"""CBC methods as plans: generators of engine messages (see messages.py)."""

from .autonomous import flutter_plan

__all__ = ["flutter_plan"]
