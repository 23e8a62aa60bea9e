"""What a fitted model says: continuation of its branches, its diagram, the metrics
against the measured orbits, and the adequacy of a start."""

from .continuation import (Branch, Equilibria, equilibrium_branch, hopf_point, orbit_at,
                           trace_flutter, trace_forced)
from .diagram import diagram_ranges, trace_diagram
from .metrics import branch_metrics
from .metrics_type import (BifurcationLocation, BranchErrors, BranchSummary, ModelMetrics,
                           PointError)

__all__ = ["BifurcationLocation", "Branch", "BranchErrors", "BranchSummary", "Equilibria",
           "ModelMetrics", "PointError", "branch_metrics", "diagram_ranges",
           "equilibrium_branch", "hopf_point", "orbit_at", "trace_diagram", "trace_flutter",
           "trace_forced"]
