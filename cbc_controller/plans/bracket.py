"""A sign change of a scalar function of one variable, narrowed by regula falsi (Illinois)
or inverse quadratic interpolation: the aerofoil plan's root bracket."""

from __future__ import annotations


class Bracket:
    """A sign change of e, [lo, hi], narrowed by regula falsi with the Illinois
    modification (an end kept twice in a row has its working value halved), or by
    inverse quadratic interpolation where three measurements allow it."""

    def __init__(self, lo, hi, elo, ehi):
        self.lo, self.hi, self.elo, self.ehi = lo, hi, elo, ehi
        self.flo, self.fhi = elo, ehi                # Illinois' working values
        self.side = 0
        self.third = None                            # the last point that left the bracket

    def falsi(self) -> float:
        return self.hi - self.fhi * (self.hi - self.lo) / (self.fhi - self.flo)

    def next(self) -> float:
        """The next target: e is strongly curved near an unstable cycle (steep above
        it, flat below), where regula falsi creeps from one side; a quadratic through
        the bracket's ends and the point before follows the curve."""
        if self.third is not None:
            pts = [(self.lo, self.elo), (self.hi, self.ehi), self.third]
            fs = [f for _, f in pts]
            if len(set(fs)) == 3:
                x = 0.0
                for i, (a, fa) in enumerate(pts):
                    others = [f for j, (_, f) in enumerate(pts) if j != i]
                    x += a * others[0] * others[1] / ((fa - others[0]) * (fa - others[1]))
                if self.lo < x < self.hi:
                    return x
        return self.falsi()

    def secant(self) -> float:
        """de/dA* across the bracket, from measured values, never the halved ones."""
        return (self.ehi - self.elo) / (self.hi - self.lo)

    def update(self, A, e) -> None:
        if (e > 0) == (self.elo > 0):
            self.third = (self.lo, self.elo)
            self.lo, self.elo, self.flo = A, e, e
            if self.side == -1:
                self.fhi /= 2
            self.side = -1
        else:
            self.third = (self.hi, self.ehi)
            self.hi, self.ehi, self.fhi = A, e, e
            if self.side == 1:
                self.flo /= 2
            self.side = 1
