"""A linear surrogate of the declared model: where an effect is and how large, before any simulation.

The response with the stop is non-linear (in contact about 60 % of the time, chaotic), but its
spectra sit between two linear systems: the stops open, and the stops closed (each replaced by
its spring). The surrogate's response PSD at the sensors is their blend

    S(f) = (1 − c) · H_open S_F H_openᴴ + c · H_closed S_F H_closedᴴ,   H = C (K − ω²M + iωD)⁻¹ B,

averaged over ``sub`` frequencies across each Welch bin (the lightly damped peaks are narrower
than a bin), on the load's band (zero above it). The weight c ∈ [0, 1] is the fraction of time
the stops are closed in the model's own simulations (measured: the power pattern of a tone over
the sensors then agrees with the record's to 10 %, where either regime alone can mislead).

Perturbations are applied in the Craig–Bampton basis of the model as given (a Rayleigh–Ritz
approximation for subsystem B, exact for A whose modes are all kept): an added mass on a tube adds
factor × that tube's mass matrix, a damping ratio ξ replaces the tube's ξ₀ by adding (ξ − ξ₀) ×
its unit-ratio modal damping, a grounded spring k at (tube, x) adds k v vᵀ. One reduction, then an
eigen-decomposition of the first-order system per evaluation: H(ω) = C V diag(1/(iω − λ)) V⁻¹ B.

The surrogate only *ranks* placements and gives first guesses (a tone's position from the
sensors' amplitude pattern at its frequency, the tube of an added mass or damping, the node of a
stop); every candidate is then fitted by simulations of the non-linear model.
"""

from __future__ import annotations

from functools import cache

import numpy as np

from tubeid.mechanics.assembly import tube_matrices
from tubeid.mechanics.effects import AddedMass, Damping
from tubeid.mechanics.reduction import reduce
from tubeid.mechanics.spec import BundleSpec, LoadPoint

__all__ = ["LinearSurrogate"]


class LinearSurrogate:
    """The blended linear response of a bundle under a load spectrum (see the module docstring).

    Parameters
    ----------
    spec : BundleSpec
        The model with the data's sensors (structural effects already applied).
    load : LoadSpectrum
        The identification load at the current r (two-sided, per Hz).
    frequency : array (F,)
        The Welch bins [Hz] (uniform from 0).
    sub : int
        Sub-frequencies per bin averaged for each bin's value.
    """

    def __init__(self, spec: BundleSpec, load, frequency, sub: int = 3):
        self.spec = spec
        self.frequency = np.asarray(frequency, dtype=float)
        self._inband = self.frequency <= load.band
        df = self.frequency[1] - self.frequency[0]
        offsets = (np.arange(sub) - (sub - 1) / 2) / sub * df
        self._fq = np.clip(self.frequency[self._inband][:, None] + offsets[None, :], 0.0, None)   # (F_b, sub)
        self._SF = load.matrix(self._fq.ravel()).reshape(self._fq.shape + (load.m, load.m))
        points = tuple(LoadPoint(name=n, tube=load.tube, x=float(x), kind=k) for n, k, x in zip(load.names, load.kinds, load.x))
        self._model = model = reduce(spec)
        self._M, self._D, self._K = (np.array(a) for a in model.mean_matrices)
        self._B, self._C = model.load_matrix(points), model.sensor_matrix()
        self._Kstop = sum((s.stiffness * np.outer(b, b) for b, s in zip(model.stop_vectors(), spec.stops)),
                          np.zeros_like(self._K))
        self._tube_parts = cache(self._tube_parts_uncached)
        self.contact = 0.5

    # ------------------------------------------------------------------ matrices
    def _tube_parts_uncached(self, tube: str) -> tuple[np.ndarray, np.ndarray]:
        """(mass, unit-ratio damping) of one tube in the reduced basis."""
        fe, T = self._model.fe, self._model.T
        t = self.spec.tube(tube)
        import dataclasses

        Mt, Dt, _ = tube_matrices(dataclasses.replace(t, damping_ratio=1.0))
        idx = np.array([i for i, d in enumerate(fe.dofs) if d[0] == tube])
        out = []
        for block in (Mt, Dt):
            full = np.zeros((fe.n_dof, fe.n_dof))
            full[np.ix_(idx, idx)] = block
            out.append(T.T @ full @ T)
        return out[0], out[1]

    def _matrices(self, effects, springs):
        M, D, K = self._M.copy(), self._D.copy(), self._K.copy()
        for e in effects:
            if isinstance(e, AddedMass):
                M += e.factor * self._tube_parts(e.tube)[0]
            elif isinstance(e, Damping):
                D += (e.ratio - self.spec.tube(e.tube).damping_ratio) * self._tube_parts(e.tube)[1]
        for tube, x, k in springs:
            v = self._model.T.T @ self._model.fe.point_vector(tube, x)
            K += k * np.outer(v, v)
        return M, D, K

    @staticmethod
    def _modal(M, D, K):
        """Eigenvalues λ (2N,), V[:N] (N, 2N) and (V⁻¹)[:, N:] M⁻¹ (2N, N) of the first-order form:
        (K − ω²M + iωD)⁻¹ = V[:N] diag(1/(iω − λ)) (V⁻¹)[:, N:] M⁻¹."""
        N = M.shape[0]
        Minv = np.linalg.inv(M)
        A = np.block([[np.zeros((N, N)), np.eye(N)], [-Minv @ K, -Minv @ D]])
        lam, V = np.linalg.eig(A)
        return lam, V[:N], np.linalg.inv(V)[:, N:] @ Minv

    @staticmethod
    def _transfer(modal, C, B, f) -> np.ndarray:
        """H(f) = C (K − ω²M + iωD)⁻¹ B: (len(f), n_out, n_in)."""
        lam, left, right = modal
        w = 2 * np.pi * np.asarray(f, dtype=float).reshape(-1)
        G = (C @ left)[None, :, :] / (1j * w[:, None, None] - lam[None, None, :])      # (f, n_out, 2N)
        return G @ (right @ B)

    def _parts(self, effects=(), springs=()) -> list[np.ndarray]:
        """The auto-PSDs (F, m) of the open and closed regimes."""
        M, D, K = self._matrices(effects, springs)
        out = []
        for Kr in (K, K + self._Kstop):
            H = self._transfer(self._modal(M, D, Kr), self._C, self._B, self._fq.ravel())
            H = H.reshape(self._fq.shape + H.shape[1:])
            S = np.real(np.einsum("fqsl,fqlk,fqsk->fqs", H, self._SF, H.conj(), optimize=True)).mean(axis=1)
            full = np.zeros((self.frequency.size, S.shape[1]))
            full[self._inband] = S
            out.append(full)
        return out

    # ------------------------------------------------------------------ public
    def psd(self, effects=(), springs=()) -> np.ndarray:
        """Blended auto-PSD (F, m) [m²/Hz] at the sensors with ``effects`` (added mass and damping;
        others are ignored) and grounded ``springs`` ((tube, x [m], stiffness [N/m]), ...); zero
        above the load's band."""
        o, c = self._parts(effects, springs)
        return (1 - self.contact) * o + self.contact * c

    def tone_pattern(self, f0: float, candidates) -> np.ndarray:
        """|H|² (blended) at ``f0`` [Hz] from a unit force at each candidate (tube, x) to every
        sensor: (n_candidates, m) [m²/N²]."""
        B = self._model.load_matrix(tuple(LoadPoint(name=f"p{i}", tube=t, x=float(x)) for i, (t, x) in enumerate(candidates)))
        o, c = (np.abs(self._transfer(self._modal(self._M, self._D, K), self._C, B, [f0])[0]).T ** 2
                for K in (self._K, self._K + self._Kstop))
        return (1 - self.contact) * o + self.contact * c
