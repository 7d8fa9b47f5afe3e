"""A model's contact working sets at its poses: the points each staged element keeps, their data as
the model's functions take it, and the checks of what a working set leaves out
(:class:`ContactSets`, a part of :class:`~kneenlp.experiment.kneemodel.KneeModel`)."""

from __future__ import annotations

import casadi as ca
import numpy as np

from kneenlp.base.compiled import BufferedCall


class ContactSets:
    """The contact working sets of a model's staged elements at its poses (a part of
    :class:`~kneenlp.experiment.kneemodel.KneeModel`, whose ``staged`` elements, ``pose_data``,
    ``pose`` function, ``parameter_names``, ``ws_size`` and ``solvers`` it uses): which sample points
    each pose's contact keeps, their packed data (and the pose data after them), what a working set
    leaves out and the share of contact at an open edge of the femoral mesh."""

    # ------------------------------------------------------------------ working sets
    def working_set(self, q: np.ndarray, theta: np.ndarray, flexion: float) -> tuple[list[np.ndarray], np.ndarray]:
        """The contact working sets at a pose: for every staged element with a working set, the
        indices of its chosen points (:meth:`StagedElement.select`) and the packed ``ws`` input of
        the model's functions (empty when no element uses working sets)."""
        if not self.ws_size:
            return [], np.zeros(0)
        R, p = (np.asarray(v) for v in self.pose(q, flexion, theta))
        values = dict(zip(self.parameter_names, np.asarray(theta, float).ravel(), strict=True))
        indices, packed = [], []
        for e in self.staged:
            if e.n_working:
                idx = e.select(R, p, values)
                indices.append(idx)
                packed.append(e.pack(idx, R, p, values))
        return indices, np.concatenate([*packed, self.pose_data_batch(R[None], p[None], values)[0]])

    def poses(self, q: np.ndarray, theta: np.ndarray, flexions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Tibial poses of the coordinates ``q`` (T x 5, SI) at ``flexions`` (T, rad): rotations
        (T x 3 x 3, tibial -> femoral) and origins (T x 3, femoral frame, m), in one mapped call."""
        q = np.asarray(q, float).reshape(-1, 5)
        n = len(q)
        call = self.solvers.get(("poses", n), lambda: BufferedCall(self.pose.map(n)))
        R, p = call(q, flexions, np.tile(theta, n))  # column-major: trial by trial
        return R.reshape(n, 3, 3).transpose(0, 2, 1), p.reshape(n, 3)

    def working_data_batch(self, q: np.ndarray, theta: np.ndarray, flexions: np.ndarray, threads: int = 1,
                           order: int = 2) -> np.ndarray:
        """The packed ``ws`` inputs (T x :attr:`ws_size`) at the poses ``q`` (T x 5, SI) and
        ``flexions`` (T, rad): every staged element's compiled pass over all poses at once, on
        ``threads`` threads.  ``order``: the residual's derivatives the data serve exactly (0: its
        value only, e.g. a line search's; 1: first derivatives, Newton's; 2: second, IPOPT's
        Hessian); higher derivatives are wrong."""
        q = np.asarray(q, float).reshape(-1, 5)
        if not self.ws_size:
            return np.zeros((len(q), 0))
        R, p = self.poses(q, theta, flexions)
        values = dict(zip(self.parameter_names, np.asarray(theta, float).ravel(), strict=True))
        return np.hstack([*[e.working_data_batch(R, p, values, threads, order) for e in self.staged if e.n_working],
                          self.pose_data_batch(R, p, values)])

    def pose_data_batch(self, R: np.ndarray, p: np.ndarray, values: dict[str, float]) -> np.ndarray:
        """The pose data (:attr:`pose_data`, the working sets' last part) at T poses (rotations
        T x 3 x 3, origins T x 3, m), T x their size."""
        return np.hstack([np.zeros((len(R), 0)), *[d.take(R, p, values) for d in self.pose_data]])

    def working_data(self, q: np.ndarray, theta: np.ndarray, flexion: float, order: int = 2) -> np.ndarray:
        """The packed ``ws`` input of the model's functions at a pose (:meth:`working_set` without
        the indices: :meth:`working_data_batch` of one pose, ``order`` as there)."""
        if not self.ws_size:
            return np.zeros(0)
        return self.working_data_batch(np.asarray(q, float)[None], theta, np.array([flexion]), order=order)[0]

    def left_out_penetration(self, q: np.ndarray, theta: np.ndarray, flexion: float,
                             indices: list[np.ndarray] | None = None) -> float:
        """Largest penetration (m) of a sample point left out of the working sets ``indices`` (by
        default those of the pose itself) at a pose (negative: every left-out point is clear of the
        surface, the working sets are valid)."""
        if not self.ws_size:
            return -np.inf
        R, p = (np.asarray(v) for v in self.pose(q, flexion, theta))
        values = dict(zip(self.parameter_names, np.asarray(theta, float).ravel(), strict=True))
        staged = [e for e in self.staged if e.n_working]
        if indices is None:
            indices = [e.select(R, p, values) for e in staged]
        worst = -np.inf
        for e, idx in zip(staged, indices, strict=True):
            near, gap = e.clearance_near(R, p, values)
            left_out = ~np.isin(near, idx)
            if np.any(left_out):
                worst = max(worst, float(-gap[left_out].min()))
        return worst

    def left_out_batch(self, q: np.ndarray, theta: np.ndarray, flexions: np.ndarray, threads: int = 1) -> np.ndarray:
        """:meth:`left_out_penetration` of the poses ``q`` (T x 5, SI) at ``flexions`` (T, rad) with
        the working sets of each pose, for all at once (positive: the pose's contact is not
        represented; -inf or negative: it is)."""
        q = np.asarray(q, float).reshape(-1, 5)
        flexions = np.asarray(flexions, float).ravel()
        worst = np.full(len(q), -np.inf)
        staged = [e for e in self.staged if e.n_working]
        if not staged:
            return worst
        R, p = self.poses(q, theta, flexions)
        for e in staged:
            if hasattr(e, "left_out_batch"):
                worst = np.maximum(worst, e.left_out_batch(R, p, threads))
            else:
                worst = np.maximum(worst, [self.left_out_penetration(q[t], theta, flexions[t]) for t in range(len(q))])
        return worst

    def rim_batch(self, q: np.ndarray, theta: np.ndarray, flexions: np.ndarray) -> np.ndarray:
        """:meth:`rim_share` of the poses ``q`` (T x 5, SI) at ``flexions`` (T, rad), all at once."""
        q = np.asarray(q, float).reshape(-1, 5)
        worst = np.zeros(len(q))
        staged = [e for e in self.staged if hasattr(e, "rim_batch")]
        if staged:
            R, p = self.poses(q, theta, flexions)
            for e in staged:
                worst = np.maximum(worst, e.rim_batch(R, p))
        return worst

    def rim_share(self, q: np.ndarray, theta: np.ndarray, flexion: float) -> float:
        """Largest share of a compartment's contact force that would come from beyond an open edge
        of the femoral mesh (0 if none; a cropped surface ends there, the contact weighed down
        across the edge: :meth:`~kneenlp.model.mesh_contact.MeshContact.rim_batch`)."""
        return float(self.rim_batch(np.asarray(q, float)[None], theta, np.array([flexion]))[0])

    def working_sets_function(self, n_trials: int, order: int = 2, threads: int = 2) -> ca.Function:
        """The working sets of ``n_trials`` poses as a CasADi function with zero derivative
        (:class:`~kneenlp.model.workingsets.WorkingSets`; ``order`` as in :meth:`working_data_batch`),
        built once per number of trials, order and threads."""
        from kneenlp.model.workingsets import WorkingSets

        return self.solvers.get(("working_sets", n_trials, order, threads), lambda: WorkingSets(
            self, n_trials, f"working_sets_{n_trials}_order{order}_{threads}", threads=threads, order=order))
