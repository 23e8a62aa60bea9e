"""The periodic objective by collocation: every orbit a free truncated Fourier series, the
model's vector field asked to match its derivative, instead of an integration from a free
initial state (the shooting of :func:`.losses.orbit_terms`).

Shooting integrates every orbit over a period at every step, a chain of a few hundred small
operations (four Runge-Kutta stages per step), and that chain, not the arithmetic, is what a
step costs on a CPU. Here
the orbit is an unknown of its own, its samples a linear map of its coefficients, and the
model is evaluated at every phase at once: the whole step is a handful of batched products.
The same terms come out (:class:`.losses.OrbitTerms`): the misfit of the samples, a *defect*
where shooting has its closure, and the stability indicators of a monodromy matrix, which is
the product of the Runge-Kutta propagators of the variational equation along the series
(each propagator a function of the Jacobian at three phases, so the product needs no
sequential integration: it is formed as a balanced tree of matrix products).

The defect is the vector field's mismatch with the series' derivative, each state over its
scale and the orbit's angular frequency, squared and averaged over the phases, times
(2 pi)^2: a constant relative mismatch delta accumulated over one period moves the end state
by 2 pi delta of the state's scale, which is what the shooting closure measures. So the two
objectives weigh a model that does not close its orbit alike, and the closure weight serves
both.

What collocation leaves out is the series' truncation: an orbit with harmonics above
:func:`harmonics_of`'s is not represented, and the monodromy matrix is a Runge-Kutta
approximation at the sample spacing (one step per sample). It is therefore the first,
long training of a start (:func:`.train._train`), which the shooting objective finishes,
from the initial states and periods collocation found (:func:`shooting_unknowns`).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..models.amplitude import resolve
from ..models.flow import ordered_product, rk4_propagator
from ..models.ude import UDE
from .identify import TrainingData
from .losses import OrbitTerms, objective_of
from .options import TrainConfig
from .penalties import penalty_sum

# phases per sample where the vector field is matched and its Jacobian taken: the variational
# integration's Runge-Kutta steps are two phases long (a step's midpoint is a phase of the
# grid), one step per sample
FINE = 2


def harmonics_of(n: int) -> int:
    """The harmonics an orbit of ``n`` samples per period carries: all below the Nyquist
    frequency (whose cosine alone the samples cannot tell from aliasing)."""
    return (n - 1) // 2


class Basis(eqx.Module):
    """Linear maps from an orbit's Fourier coefficients (``2k + 1`` per state, a0, a1..ak,
    b1..bk) to its samples at the ``n`` measured phases, and to its values and phase
    derivatives at ``FINE * n`` phases; and the analysis map from the samples back."""
    analysis: jax.Array     # (2k+1, n)
    samples: jax.Array      # (n, 2k+1)
    fine: jax.Array         # (FINE n, 2k+1)
    fine_slope: jax.Array   # (FINE n, 2k+1): d/dphi

    @staticmethod
    def of(n: int) -> "Basis":
        k = harmonics_of(n)
        j = np.arange(1, k + 1)

        def synth(phi):
            return np.concatenate([np.ones((phi.size, 1)), np.cos(np.outer(phi, j)),
                                   np.sin(np.outer(phi, j))], axis=1)

        def slope(phi):
            return np.concatenate([np.zeros((phi.size, 1)), -j * np.sin(np.outer(phi, j)),
                                   j * np.cos(np.outer(phi, j))], axis=1)

        phi = 2 * np.pi * np.arange(n) / n
        fine = 2 * np.pi * np.arange(FINE * n) / (FINE * n)
        analysis = np.concatenate([np.full((1, n), 1.0 / n), 2.0 / n * np.cos(np.outer(j, phi)),
                                   2.0 / n * np.sin(np.outer(j, phi))], axis=0)
        return Basis(jnp.asarray(analysis), jnp.asarray(synth(phi)),
                     jnp.asarray(synth(fine)), jnp.asarray(slope(fine)))


def collocation_unknowns(data: TrainingData, autonomous: bool, lead: tuple = ()) -> dict:
    """Collocation's unknowns besides the model, scaled offsets from the measured values:
    every orbit's Fourier coefficients (each state over its scale), its period where the
    system is autonomous, its parameter where the data says it may be in error."""
    n_o, n, n_s = data.ys.shape
    unknowns = {"dC": jnp.zeros(lead + (n_o, 2 * harmonics_of(n) + 1, n_s))}
    if autonomous:
        unknowns["dT"] = jnp.zeros(lead + data.period.shape)
    if data.param_errors is not None:
        unknowns["dP"] = jnp.zeros(lead + data.period.shape)
    return unknowns


def _harmonic_order(n: int) -> np.ndarray:
    """(2k + 1, 1) each coefficient's harmonic number, the mean's counted as 1."""
    k = harmonics_of(n)
    j = np.arange(1, k + 1)
    return np.concatenate([[1], j, j]).astype(float)[:, None]


def _orbit_series(basis: Basis, data: TrainingData, dC):
    """Every orbit's coefficients: the measured samples' plus the offsets, harmonic j's
    over j. The derivative multiplies harmonic j by j, so a step of one size in every
    unknown moves the orbit's derivative by one size in every harmonic: an optimiser whose
    steps are scale-free (Adam) then does not stir the high harmonics, whose own values are
    small, into a defect larger than the fit it is after."""
    C0 = jnp.einsum("kn,ons->oks", basis.analysis, data.ys)
    return C0 + dC * data.y_scale / _harmonic_order(data.ys.shape[1])


def shooting_unknowns(params: dict, data: TrainingData) -> dict:
    """The shooting objective's unknowns (:func:`.losses.orbit_unknowns`) where collocation
    left the orbits: each initial state the series' value at phase 0 (a shooting orbit
    starts at the first measured sample's phase), the period and parameter offsets as they
    are."""
    basis = Basis.of(data.ys.shape[1])
    C = _orbit_series(basis, data, params["dC"])
    y0 = C[..., 0, :] + jnp.sum(C[..., 1:harmonics_of(data.ys.shape[1]) + 1, :], axis=-2)
    out = {"dy0": (y0 - data.ys[:, 0, :]) / data.y_scale}
    return {**out, **{k: v for k, v in params.items() if k in ("dT", "dP")}}


def monodromy(J, T):
    """The monodromy matrix from the Jacobians ``J`` (FINE n, s, s) at the fine phases of
    one period ``T``: Runge-Kutta steps two phases long."""
    m = J.shape[0]
    J0, Jm = J[0::2], J[1::2]
    J1 = jnp.roll(J, -2, axis=0)[0::2]          # the period's end is its start
    stages = jnp.stack([J0, Jm, Jm, J1], axis=1)        # (steps, 4, s, s)
    return ordered_product(jax.vmap(rk4_propagator, (0, None))(stages, 2.0 * T / m))


def collocation_terms(model, params, data: TrainingData, cfg: TrainConfig) -> OrbitTerms:
    """Every orbit of ``data`` as the series in ``params``: its misfit to the measured
    samples, its defect as the model's orbit (in the closure's place), and its stability
    from the variational equation along it."""
    mech = model.mech
    n = data.ys.shape[1]
    basis = Basis.of(n)
    C = _orbit_series(basis, data, params["dC"])          # (orbits, 2k+1, states)
    autonomous = mech.autonomous
    T = data.period * (1.0 + params["dT"]) if autonomous else data.period
    drive, prior = data.drive, jnp.zeros(data.period.shape)
    if "dP" in params:
        errors = data.param_errors
        drive = eqx.tree_at(lambda d: d.param, drive, drive.param + errors.sigma * params["dP"])
        prior = errors.cost * params["dP"] ** 2
    state_weight = (jnp.ones(data.ys.shape[::2]) if data.state_weight is None
                    else data.state_weight)
    t_fine = jnp.arange(FINE * n) / (FINE * n)

    def one(ys, Ck, T, drive, sw):
        if autonomous:      # an imposed input is periodic in the orbit's own period
            drive = eqx.tree_at(lambda d: d.omega, drive, 2.0 * jnp.pi / T)
        frozen = model.at_drive(drive)
        omega = 2.0 * jnp.pi / T
        sim = basis.samples @ Ck
        fit = jnp.mean(((sim - ys) / data.y_scale) ** 2 * sw) / jnp.mean(sw)
        y = basis.fine @ Ck
        dy = omega * (basis.fine_slope @ Ck)

        def field(t, yy):
            f = frozen.vector_field(t, yy, drive)
            return f, f
        J, f = jax.vmap(jax.jacfwd(field, argnums=1, has_aux=True))(T * t_fine, y)
        defect = (2.0 * jnp.pi) ** 2 * jnp.sum(
            jnp.mean(((dy - f) / (omega * data.y_scale)) ** 2, axis=0))
        M = monodromy(J, T)
        fold = mech.stability_indicator(M)
        secondary = (mech.secondary_indicators(M, fold) if mech.holds_secondary_tests
                     else jnp.full(2, jnp.inf))
        return fit, defect, fold, secondary

    fit, defect, indicator, secondary = jax.vmap(one)(data.ys, C, T, drive, state_weight)
    return OrbitTerms(fit, defect, indicator, secondary, prior)


def collocation_loss(params, static, mech, data: TrainingData, cfg: TrainConfig, reg=None):
    """The periodic objective with every orbit collocated, plus the penalties that act in
    the periodic stage."""
    model = resolve(UDE(mech, eqx.combine(params["corr"], static)))
    terms = collocation_terms(model, params, data, cfg)
    return objective_of(terms, data, cfg) + penalty_sum(cfg.penalties, "periodic", model, reg)
