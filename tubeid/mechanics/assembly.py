"""Finite-element assembly of a tube bundle: Hermite Euler-beam elements, springs, modal damping.

Each tube node carries two DOFs, the transverse displacement ``y`` [m] and the rotation
``theta`` [rad]. Elements are cubic Hermite (Euler–Bernoulli) with consistent mass. Constrained
DOFs (clamped: y and θ; pinned: y) are removed. Damping is modal per tube: for each tube alone
(its own end conditions, no links), D_t = M_t Φ diag(2 ξ ω) Φᵀ M_t with mass-normalised Φ; springs
and stops are undamped.

The assembled matrices are kept split by subsystem: A (the non-linear tube and links from it to
the ground) and B (all other tubes and all links that are not internal to A), so that the
Craig–Bampton reduction of B and the condensed stiffness on the A–B interface follow directly.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
import scipy.linalg

from tubeid._validation import on_tube
from tubeid.errors import SpecificationError
from tubeid.mechanics.spec import BundleSpec, LoadPoint, SensorSpec, TubeSpec

__all__ = ["beam_element", "hermite_shape", "FEModel", "assemble", "tube_matrices"]


def beam_element(E: float, I: float, rho: float, A: float, le: float) -> tuple[np.ndarray, np.ndarray]:
    """Stiffness [N/m…] and consistent mass [kg…] of one Hermite element, DOFs (y1, θ1, y2, θ2)."""
    L = le
    k = E * I / L**3 * np.array(
        [[12, 6 * L, -12, 6 * L], [6 * L, 4 * L * L, -6 * L, 2 * L * L], [-12, -6 * L, 12, -6 * L], [6 * L, 2 * L * L, -6 * L, 4 * L * L]]
    )
    m = rho * A * L / 420.0 * np.array(
        [[156, 22 * L, 54, -13 * L], [22 * L, 4 * L * L, 13 * L, -3 * L * L], [54, 13 * L, 156, -22 * L], [-13 * L, -3 * L * L, -22 * L, 4 * L * L]]
    )
    return k, m


def hermite_shape(xi: float, le: float, derivative: int = 0) -> np.ndarray:
    """Hermite shape functions (or their x-derivative) at local coordinate ξ ∈ [0, 1]."""
    if derivative == 0:
        return np.array([1 - 3 * xi**2 + 2 * xi**3, le * (xi - 2 * xi**2 + xi**3), 3 * xi**2 - 2 * xi**3, le * (-(xi**2) + xi**3)])
    if derivative == 1:
        return np.array([(-6 * xi + 6 * xi**2) / le, 1 - 4 * xi + 3 * xi**2, (6 * xi - 6 * xi**2) / le, -2 * xi + 3 * xi**2])
    raise ValueError("derivative must be 0 or 1")


def _free_mask(tube: TubeSpec) -> np.ndarray:
    n_nodes = tube.n_elements + 1
    free = np.ones(2 * n_nodes, dtype=bool)
    for end, node in zip(tube.ends, (0, n_nodes - 1)):
        if end in ("clamped", "pinned"):
            free[2 * node] = False
        if end == "clamped":
            free[2 * node + 1] = False
    return free


def tube_matrices(tube: TubeSpec) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(M, D, K) of one tube alone on its free DOFs, with its modal damping."""
    n_nodes = tube.n_elements + 1
    le = tube.length / tube.n_elements
    ke, me = beam_element(tube.youngs_modulus, tube.inertia, tube.density, tube.area, le)
    K = np.zeros((2 * n_nodes, 2 * n_nodes))
    M = np.zeros_like(K)
    for e in range(tube.n_elements):
        s = slice(2 * e, 2 * e + 4)
        K[s, s] += ke
        M[s, s] += me
    free = _free_mask(tube)
    K, M = K[np.ix_(free, free)], M[np.ix_(free, free)]
    D = np.zeros_like(K)
    if tube.damping_ratio > 0 and K.size:
        w2, phi = scipy.linalg.eigh(K, M)
        if w2.min() <= 0:  # rigid-body modes of a free tube are not damped
            w2 = np.clip(w2, 0.0, None)
        Mphi = M @ phi
        D = Mphi @ np.diag(2 * tube.damping_ratio * np.sqrt(w2)) @ Mphi.T
    return M, D, K


@dataclass(frozen=True, eq=False)
class FEModel:
    """Assembled finite-element model of a bundle (stops open). Made by :func:`assemble`.

    Parameters
    ----------
    spec : BundleSpec
        The specification it was assembled from.
    dofs : tuple of (str, int, str)
        One ``(tube, node, "y" | "theta")`` per free DOF, in matrix order.
    M, D, K : numpy.ndarray
        Full (n_dof, n_dof) mass, damping and stiffness matrices (kg, N·s/m, N/m on ``y`` DOFs;
        the matching moment units on ``theta`` DOFs).
    parts : dict
        ``{"A": (M, D, K), "B": (M, D, K)}``: the contributions of subsystem A (the non-linear
        tube and its links to the ground) and B (the rest), summing to the full matrices.
    interface : numpy.ndarray
        Indices of the A–B coupling DOFs (A's ``y`` at linked nodes, by increasing x).
    """

    spec: BundleSpec
    dofs: tuple[tuple[str, int, str], ...]
    M: np.ndarray
    D: np.ndarray
    K: np.ndarray
    parts: dict = field(repr=False)
    interface: np.ndarray

    @property
    def n_dof(self) -> int:
        """Number of free DOFs."""
        return len(self.dofs)

    @cached_property
    def _offsets(self) -> dict[str, dict[tuple[int, str], int]]:
        out: dict[str, dict[tuple[int, str], int]] = {}
        for i, (t, node, kind) in enumerate(self.dofs):
            out.setdefault(t, {})[(node, kind)] = i
        return out

    def dof_index(self, tube: str, node: int, kind: str = "y") -> int | None:
        """Global index of a DOF.

        Parameters
        ----------
        tube : str
            Tube name.
        node : int
            Node index along the tube (0 at x = 0).
        kind : str
            ``"y"`` (transverse displacement) or ``"theta"`` (rotation).

        Returns
        -------
        int or None
            The row/column of the matrices, or None when the DOF is constrained.
        """
        return self._offsets.get(tube, {}).get((node, kind))

    def point_vector(self, tube: str, x: float, derivative: int = 0) -> np.ndarray:
        """Row vector v with v·u = y(x) (derivative 0) or θ(x) = y'(x) (derivative 1) on ``tube``.

        By virtue of virtual work, v is also the generalised force of a unit transverse force
        (derivative 0) or unit moment (derivative 1) applied at x.

        Parameters
        ----------
        tube : str
            Tube name.
        x : float
            Abscissa [m], anywhere on the tube: in [0, length] (Hermite interpolation between nodes);
            a point off the tube is refused (the shape functions would extrapolate).
        derivative : int
            0 for the displacement, 1 for the rotation.

        Returns
        -------
        numpy.ndarray
            Shape (n_dof,).
        """
        t = self.spec.tube(tube)
        on_tube("x", t, x, "the point")
        le = t.length / t.n_elements
        e = min(int(np.floor(x / le)), t.n_elements - 1)
        e = max(e, 0)
        shape = hermite_shape((x - e * le) / le, le, derivative)
        v = np.zeros(self.n_dof)
        for local, (node, kind) in enumerate(((e, "y"), (e, "theta"), (e + 1, "y"), (e + 1, "theta"))):
            i = self.dof_index(tube, node, kind)
            if i is not None:
                v[i] += shape[local]
        return v

    def load_matrix(self, points: tuple[LoadPoint, ...] | None = None) -> np.ndarray:
        """Influence matrix of load points (force → y, moment → θ).

        Parameters
        ----------
        points : tuple of LoadPoint, optional
            The load points (default: the specification's ``loads``).

        Returns
        -------
        numpy.ndarray
            Shape (n_dof, m), one column per point: the generalised force of a unit load.
        """
        pts = self.spec.loads if points is None else points
        for i, p in enumerate(pts):
            on_tube(f"points[{i}].x", self.spec.tube(p.tube), p.x, f"load point {p.name!r}")
        cols = [self.point_vector(p.tube, p.x, 1 if p.kind == "moment" else 0) for p in pts]
        return np.stack(cols, axis=1) if cols else np.zeros((self.n_dof, 0))

    def sensor_matrix(self, sensors: tuple[SensorSpec, ...] | None = None) -> np.ndarray:
        """Observation matrix of transverse-displacement sensors.

        Parameters
        ----------
        sensors : tuple of SensorSpec, optional
            The sensors (default: the specification's ``sensors``).

        Returns
        -------
        numpy.ndarray
            Shape (n_sensors, n_dof): sensor displacements [m] = matrix @ u.
        """
        ss = self.spec.sensors if sensors is None else sensors
        for i, p in enumerate(ss):
            on_tube(f"sensors[{i}].x", self.spec.tube(p.tube), p.x, f"sensor {p.name!r}")
        rows = [self.point_vector(s.tube, s.x) for s in ss]
        return np.stack(rows) if rows else np.zeros((0, self.n_dof))

    def stop_vectors(self) -> np.ndarray:
        """The stops' observation rows.

        Returns
        -------
        numpy.ndarray
            Shape (n_stops, n_dof): rows b with u_stop = b·u [m].
        """
        rows = [self.point_vector(s.tube, s.x) for s in self.spec.stops]
        return np.stack(rows) if rows else np.zeros((0, self.n_dof))

    def eigenfrequencies(self, n: int | None = 10) -> np.ndarray:
        """Undamped eigenfrequencies of the linear model (stops open).

        Parameters
        ----------
        n : int, optional
            How many, lowest first; None for all.

        Returns
        -------
        numpy.ndarray
            Frequencies [Hz], ascending.
        """
        w2 = scipy.linalg.eigh(self.K, self.M, eigvals_only=True)
        f = np.sqrt(np.clip(w2, 0, None)) / (2 * np.pi)
        return f if n is None else f[:n]


def assemble(spec: BundleSpec) -> FEModel:
    """Assemble a :class:`FEModel` from a validated specification.

    Parameters
    ----------
    spec : BundleSpec
        The bundle.

    Returns
    -------
    FEModel
        Its matrices split by subsystem and its A–B interface; a bundle with a rigid-body mode
        raises ``SpecificationError``.
    """
    dofs: list[tuple[str, int, str]] = []
    blocks = []
    for t in spec.tubes:
        free = _free_mask(t)
        names = [(t.name, n, k) for n in range(t.n_elements + 1) for k in ("y", "theta")]
        start = len(dofs)
        dofs.extend(d for d, f in zip(names, free) if f)
        blocks.append((t, slice(start, len(dofs))))
    n = len(dofs)
    a_name = spec.a_tube
    parts = {p: [np.zeros((n, n)) for _ in range(3)] for p in ("A", "B")}
    for t, s in blocks:
        part = "A" if t.name == a_name else "B"
        for mat, block in zip(parts[part], tube_matrices(t)):
            mat[s, s] += block
    index = {d: i for i, d in enumerate(dofs)}
    interface: set[int] = set()
    for i, link in enumerate(spec.links):
        ta = spec.tube(link.tube)
        ia = index.get((link.tube, ta.node_index(link.x), "y"))
        ib = None
        if link.to_tube is not None:
            tb = spec.tube(link.to_tube)
            ib = index.get((link.to_tube, tb.node_index(link.other_x), "y"))
        v = np.zeros(n)
        if ia is not None:
            v[ia] += 1.0
        if ib is not None:
            v[ib] -= 1.0
        if not v.any():
            continue  # both ends constrained: the spring carries nothing
        internal_a = link.tube == a_name and link.to_tube in (None, a_name)
        internal_a |= link.to_tube == a_name and link.tube == a_name
        parts["A" if internal_a else "B"][2][...] += link.stiffness * np.outer(v, v)
        if not internal_a and a_name is not None:
            for tube_name, idx in ((link.tube, ia), (link.to_tube, ib)):
                if tube_name == a_name and idx is not None:
                    interface.add(idx)
    M = parts["A"][0] + parts["B"][0]
    D = parts["A"][1] + parts["B"][1]
    K = parts["A"][2] + parts["B"][2]
    try:
        np.linalg.cholesky(K)
    except np.linalg.LinAlgError:
        raise SpecificationError("tubes[*].ends / links", spec.name, "the bundle has a rigid-body mode (stiffness matrix singular): clamp, pin or link every tube") from None
    iface = np.array(sorted(interface, key=lambda i: dofs[i][1]), dtype=int)
    return FEModel(spec=spec, dofs=tuple(dofs), M=M, D=D, K=K, parts={p: tuple(v) for p, v in parts.items()}, interface=iface)
