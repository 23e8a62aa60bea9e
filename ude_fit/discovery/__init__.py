"""Naming the missing physics: explain the residual as library effects, add them to the
mechanistic model, refit, and close the loop while the diagram improves."""

from .explain import Explanation, explain
from .loop import LoopResult, close_loop, refine

__all__ = ["Explanation", "LoopResult", "close_loop", "explain", "refine"]
