"""Working sets as a function of the pose inside CasADi graphs, with zero derivative.

:meth:`KneeModel.working_set` takes, at a pose, the data of the contact points that can touch
(and, for mesh contact, the surface's expansion at each of them).  :class:`WorkingSets` wraps it as
a CasADi function of the poses of ``T`` trials (``q`` 5 x T, ``theta``, ``flexion`` 1 x T ->
``ws`` ws_size x T) whose derivative is declared structurally zero.  Feeding it to the model's
residual gives the *equilibrium* function: at every point a solver evaluates it, its value and its
first derivatives are those of the contact surfaces themselves (the working-set data equal them
to first order at the point where they are taken), and the second derivatives omit only the
third derivatives of the femoral distance field (piecewise constant in a cubic spline).  So the
forward Newton iteration and IPOPT work on the exact contact model without re-solves.

``order`` (:meth:`KneeModel.working_data_batch`): the derivatives the data serve, 1 for Newton's
iteration and the sensitivities (:meth:`KneeModel.trial_derivatives`), 2 for IPOPT.

The last evaluation is memoised: a solver evaluates value, Jacobian and Hessian at the same point,
so IPOPT's data are taken with the Hessian's expansion (``order=2``) even for a value: IPOPT evaluates
its derivatives at almost every point whose value it evaluates, and one pass of order 2 (~19 ms
for Set 4 on the default knee) costs less than a value pass (~10 ms) followed by it.  Set 4, 5
seeds: IPOPT 0.82 -> 0.68 s median.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from kneenlp.base import interrupts


class WorkingSets(ca.Callback):
    """``(q, theta, flexion) -> ws`` for ``n_trials`` trials of ``model`` (see module docstring)."""

    def __init__(self, model, n_trials: int, name: str = "working_sets", threads: int = 2, order: int = 2):
        ca.Callback.__init__(self)
        self.model, self.n_trials = model, int(n_trials)
        self.threads = max(1, int(threads))
        self.order = int(order)
        self.n_theta = len(model.parameter_names)
        self._key: bytes | None = None
        self._value: np.ndarray | None = None
        self.construct(name, {})

    def get_n_in(self) -> int:
        return 3

    def get_n_out(self) -> int:
        return 1

    def get_name_in(self, i: int) -> str:
        return ("q", "theta", "flexion")[i]

    def get_name_out(self, i: int) -> str:
        return "ws"

    def get_sparsity_in(self, i: int) -> ca.Sparsity:
        return ca.Sparsity.dense(*((5, self.n_trials), (self.n_theta, 1), (1, self.n_trials))[i])

    def get_sparsity_out(self, i: int) -> ca.Sparsity:
        return ca.Sparsity.dense(self.model.ws_size, self.n_trials)

    def has_eval_buffer(self) -> bool:
        return True

    def eval_buffer(self, arg, res) -> int:
        """Zero-copy evaluation (the working sets are large: ~1e4 numbers per trial)."""
        q = np.frombuffer(arg[0], dtype=np.float64).reshape(self.n_trials, 5)  # column-major 5 x T
        theta = np.frombuffer(arg[1], dtype=np.float64)
        flexion = np.frombuffer(arg[2], dtype=np.float64)
        key = q.tobytes() + theta.tobytes() + flexion.tobytes()
        if key != self._key:
            with interrupts.held():  # a signal here is raised by the caller, not printed by CasADi
                self._value = self.model.working_data_batch(q, theta, flexion, self.threads, self.order).ravel()
            self._key = key
        np.frombuffer(res[0], dtype=np.float64)[:] = self._value
        return 0

    def has_jacobian(self) -> bool:
        return True

    def get_jacobian(self, name, inames, onames, opts):
        ins = [ca.MX.sym(n, self.get_sparsity_in(i)) for i, n in enumerate(inames[:3])]
        ins.append(ca.MX.sym(inames[3], self.get_sparsity_out(0)))
        rows = self.model.ws_size * self.n_trials
        outs = [ca.MX(ca.Sparsity(rows, self.get_sparsity_in(i).numel())) for i in range(3)]
        return ca.Function(name, ins, outs, inames, onames, opts)
