"""The paper's neural-network drift predictor, in torch.

Yang, Jagannathan & Bohannan (IEEE T-Nano 2008, section IV) predict the next
frame's drift with a two-layer network: the last N = 8 drift increments and the
temperature as inputs, 50 tanh hidden units, a linear output; trained by
Levenberg–Marquardt on the first 20 points, then online on the most recent 50
at every frame. This module follows that recipe:

* **Inputs** (per sample j): the N previous increments d_{j−N}..d_{j−1}
  (d_j = p_j − p_{j−1}, nm, divided by the RMS increment of the initial data)
  and each configured channel at the time of the previous frame (standardised
  by the initial data). **Target**: d_j, same scaling.
* **Per axis** (default): one net per axis with inputs N increments of that
  axis + channels and one output; **joint**: one net with 2N + channels inputs
  and two outputs. The paper does not say which; per axis has fewer weights.
* **Training**: once ``initial_points`` drift points exist (the paper's 20;
  they give 20 − N − 1 training pairs), ``initial_iterations`` LM iterations
  from a seeded random start; afterwards ``online_iterations`` LM iterations
  per frame on the most recent ``window`` pairs, warm-started. Before the first
  fit the predictor extrapolates the last increment (constant velocity).
* **LM step**: residuals r = y − f(θ), Jacobian J = ∂f/∂θ by
  ``torch.func.jacrev``; step δ = (JᵀJ + λI)⁻¹Jᵀr, computed as
  δ = Jᵀ(JJᵀ + λI)⁻¹r when there are fewer residuals than weights (same
  vector, much smaller solve). λ is divided by 10 after a step that lowers the
  cost and multiplied by 10 (step rejected) otherwise (Marquardt 1963).
* **Determinism**: float64, weights drawn from a ``torch.Generator`` seeded with
  ``seed``, and torch limited to ``threads`` threads while training.
* **Horizon**: the net predicts one frame ahead; p̂(t) = p_n + d̂·(t − t_n)/Δ
  with Δ the median frame period.
"""

from __future__ import annotations

import contextlib
import logging
import math
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import numpy as np
import numpy.typing as npt
import torch
from torch.func import jacrev

from afmdrift.config import NNConfig
from afmdrift.model._base import History, Observation, Prediction
from afmdrift.model._baselines import ObservationLog, _LoggingPredictor, as_times

__all__ = ["NNPredictor", "NNSeriesModel", "lm_fit", "lm_solve"]

_log = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]


@contextlib.contextmanager
def torch_threads(n: int) -> Iterator[None]:
    """Limit torch to ``n`` intra-op threads inside the block (restored after)."""
    old = torch.get_num_threads()
    if old != n:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        if old != n:
            torch.set_num_threads(old)


def mlp(theta: torch.Tensor, x: torch.Tensor, n_in: int, n_hidden: int, n_out: int) -> torch.Tensor:
    """Two-layer perceptron y = W₂·tanh(W₁x + b₁) + b₂ with flat weights ``theta``.

    ``x`` has shape (m, n_in); returns (m, n_out).
    """
    i = 0
    w1 = theta[i : i + n_hidden * n_in].view(n_hidden, n_in)
    i += n_hidden * n_in
    b1 = theta[i : i + n_hidden]
    i += n_hidden
    w2 = theta[i : i + n_out * n_hidden].view(n_out, n_hidden)
    i += n_out * n_hidden
    b2 = theta[i : i + n_out]
    return torch.tanh(x @ w1.T + b1) @ w2.T + b2


def n_weights(n_in: int, n_hidden: int, n_out: int) -> int:
    return n_hidden * n_in + n_hidden + n_out * n_hidden + n_out


def init_weights(n_in: int, n_hidden: int, n_out: int, generator: torch.Generator) -> torch.Tensor:
    """Uniform(±1/√fan_in) weights, zero output bias, float64."""
    parts = [
        (torch.rand(n_hidden * n_in, generator=generator, dtype=torch.float64) * 2 - 1)
        / math.sqrt(n_in),
        (torch.rand(n_hidden, generator=generator, dtype=torch.float64) * 2 - 1) / math.sqrt(n_in),
        (torch.rand(n_out * n_hidden, generator=generator, dtype=torch.float64) * 2 - 1)
        / math.sqrt(n_hidden),
        torch.zeros(n_out, dtype=torch.float64),
    ]
    return torch.cat(parts)


def lm_solve(
    f: Callable[[torch.Tensor], torch.Tensor],
    theta: torch.Tensor,
    target: torch.Tensor,
    *,
    iterations: int,
    damping: float,
) -> tuple[torch.Tensor, float, float]:
    """Levenberg–Marquardt minimisation of ‖target − f(θ)‖².

    Parameters
    ----------
    f : callable
        Model, θ (P,) → predictions (m,).
    theta : Tensor, shape (P,)
        Starting parameters (float64).
    target : Tensor, shape (m,)
    iterations : int
        Maximum number of LM iterations (each recomputes the Jacobian by
        ``torch.func.jacrev``; within one, λ grows ×10 until a step lowers the cost).
    damping : float
        Starting λ.

    Returns
    -------
    theta, cost, damping
        Final parameters, final sum of squared residuals and the adapted λ (to
        warm-start the next call).
    """
    r = target - f(theta)
    cost = float(r @ r)
    lam = float(damping)
    m, p = target.numel(), theta.numel()
    for _ in range(iterations):
        jac = jacrev(f)(theta)
        accepted = False
        improvement = 0.0
        for _attempt in range(12):
            if m <= p:
                a = jac @ jac.T + lam * torch.eye(m, dtype=theta.dtype)
                delta = jac.T @ torch.linalg.solve(a, r)
            else:
                a = jac.T @ jac + lam * torch.eye(p, dtype=theta.dtype)
                delta = torch.linalg.solve(a, jac.T @ r)
            trial = theta + delta
            r_trial = target - f(trial)
            cost_trial = float(r_trial @ r_trial)
            if math.isfinite(cost_trial) and cost_trial < cost:
                theta, r, lam = trial, r_trial, max(lam / 10.0, 1e-12)
                improvement = cost - cost_trial
                cost = cost_trial
                accepted = True
                break
            lam = min(lam * 10.0, 1e12)
        if not accepted or improvement <= 1e-14 * max(cost, 1e-300):
            break
    return theta, cost, lam


def lm_fit(
    theta: torch.Tensor,
    x: torch.Tensor,
    y: torch.Tensor,
    *,
    shape: tuple[int, int, int],
    iterations: int,
    damping: float,
) -> tuple[torch.Tensor, float, float]:
    """:func:`lm_solve` for one :func:`mlp` with inputs ``x`` (m, n_in) and targets
    ``y`` (m, n_out); ``shape`` is (n_in, n_hidden, n_out)."""
    n_in, n_hidden, n_out = shape

    def f(th: torch.Tensor) -> torch.Tensor:
        return mlp(th, x, n_in, n_hidden, n_out).reshape(-1)

    return lm_solve(f, theta, y.reshape(-1), iterations=iterations, damping=damping)


class NNSeriesModel:
    """The paper's network on a generic 2-D series (drift, or a model residual).

    Feed the whole series with :meth:`fit` after each new point and ask for the
    next increment with :meth:`next_increment`.
    """

    def __init__(self, config: NNConfig) -> None:
        self.config = config
        self.trained = False
        self.inc_scale = np.ones(2)
        self.chan_mean = np.zeros(len(config.channels))
        self.chan_scale = np.ones(len(config.channels))
        n_in, _, n_out = self._shape()
        gen = torch.Generator().manual_seed(config.seed)
        nets = 1 if config.joint else 2
        self.theta = [init_weights(n_in, config.hidden, n_out, gen) for _ in range(nets)]
        self.damping = [float(config.damping)] * nets
        self.last_cost = [math.nan] * nets

    def _shape(self) -> tuple[int, int, int]:
        c = len(self.config.channels)
        n = self.config.lags
        if self.config.joint:
            return 2 * n + c, self.config.hidden, 2
        return n + c, self.config.hidden, 1

    def _inputs(self, z_inc: FloatArray, z_chan: FloatArray, axis: int | None) -> FloatArray:
        """Network inputs for j = N..k, shape (k − N + 1, n_in).

        ``z_inc`` (k, 2) are scaled increments (z_inc[j] = p_{j+1} − p_j),
        ``z_chan`` (k + 1, C) standardised channels at each point. Row j holds
        z_inc[j−N..j−1] and the channels at point j (the last frame known when
        predicting increment j); its target is z_inc[j] (the last row has none
        yet: it is the input for the next prediction).
        """
        n = self.config.lags
        k = z_inc.shape[0]
        rows = []
        for j in range(n, k + 1):
            lagged = z_inc[j - n : j]
            part = lagged.ravel() if axis is None else lagged[:, axis]
            rows.append(np.concatenate([part, z_chan[j]]))
        return np.asarray(rows, dtype=np.float64).reshape(-1, self._shape()[0])

    def _standardise(self, values: FloatArray, chans: FloatArray) -> tuple[FloatArray, FloatArray]:
        z_inc = np.diff(values, axis=0) / self.inc_scale
        z_chan = np.nan_to_num((chans - self.chan_mean) / self.chan_scale)
        return z_inc, z_chan

    def fit(self, values: FloatArray, chans: FloatArray) -> None:
        """Train on the series ``values`` (n, 2) with channels (n, C) at each point."""
        cfg = self.config
        n_points = values.shape[0]
        if n_points < cfg.initial_points or n_points < cfg.lags + 2:
            return
        if not self.trained:
            incs = np.diff(values, axis=0)
            rms = np.sqrt(np.mean(incs**2, axis=0))
            self.inc_scale = np.where(rms > 1e-9, rms, 1.0)
            if chans.shape[1]:
                self.chan_mean = np.nanmean(chans, axis=0)
                sd = np.nanstd(chans, axis=0)
                self.chan_scale = np.where(sd > 1e-3, sd, 1.0)
        if self.trained:
            # Online: only the most recent `window` pairs are used; build no more.
            keep = cfg.window + cfg.lags + 1
            values, chans = values[-keep:], chans[-keep:]
        z_inc, z_chan = self._standardise(values, chans)
        iterations = cfg.online_iterations if self.trained else cfg.initial_iterations
        shape = self._shape()
        targets = z_inc[cfg.lags :]
        with torch_threads(cfg.threads):
            for net in range(len(self.theta)):
                x = self._inputs(z_inc, z_chan, None if cfg.joint else net)[:-1]
                y = targets if cfg.joint else targets[:, net : net + 1]
                theta, cost, lam = lm_fit(
                    self.theta[net],
                    torch.from_numpy(np.ascontiguousarray(x[-cfg.window :])),
                    torch.from_numpy(np.ascontiguousarray(y[-cfg.window :])),
                    shape=shape,
                    iterations=iterations,
                    damping=self.damping[net],
                )
                self.theta[net], self.last_cost[net], self.damping[net] = theta, cost, lam
        self.trained = True

    def next_increment(self, values: FloatArray, chans: FloatArray) -> FloatArray | None:
        """Predicted next increment (2,) in nm, or ``None`` before training.

        ``values`` (n, 2) is the series so far, ``chans`` (n, C) the channels at
        each point (only the last N + 1 points are used).
        """
        cfg = self.config
        if not self.trained or values.shape[0] < cfg.lags + 1:
            return None
        z_inc, z_chan = self._standardise(values[-cfg.lags - 1 :], chans[-cfg.lags - 1 :])
        shape = self._shape()
        out = np.zeros(2)
        with torch.no_grad():
            for net in range(len(self.theta)):
                x = self._inputs(z_inc, z_chan, None if cfg.joint else net)[-1:]
                y = mlp(self.theta[net], torch.from_numpy(x), *shape).numpy()[0]
                if cfg.joint:
                    out[:] = y
                else:
                    out[net] = y[0]
        return np.asarray(out * self.inc_scale, dtype=np.float64)

    def state_dict(self) -> dict[str, Any]:
        return {
            "config": self.config.model_dump(),
            "trained": self.trained,
            "inc_scale": self.inc_scale.tolist(),
            "chan_mean": self.chan_mean.tolist(),
            "chan_scale": self.chan_scale.tolist(),
            "theta": [t.tolist() for t in self.theta],
            "damping": list(self.damping),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.config = NNConfig.model_validate(state["config"])
        self.trained = bool(state["trained"])
        self.inc_scale = np.asarray(state["inc_scale"], dtype=np.float64)
        self.chan_mean = np.asarray(state["chan_mean"], dtype=np.float64)
        self.chan_scale = np.asarray(state["chan_scale"], dtype=np.float64)
        self.theta = [torch.tensor(t, dtype=torch.float64) for t in state["theta"]]
        self.damping = [float(v) for v in state["damping"]]
        self.last_cost = [math.nan] * len(self.theta)


def channel_matrix(history: History, names: Sequence[str], t_s: FloatArray) -> FloatArray:
    """Channels ``names`` at ``t_s``, shape (n, C); a channel not logged is 0."""
    cols = []
    for name in names:
        if name in history.channels:
            cols.append(history.channel_at(name, t_s))
        else:
            cols.append(np.zeros_like(t_s))
    return np.column_stack(cols) if cols else np.zeros((t_s.size, 0))


class NNPredictor(_LoggingPredictor):
    """The paper's NN predicting the next drift increment (see module docstring)."""

    name = "nn"

    def __init__(self, config: NNConfig | None = None) -> None:
        super().__init__()
        self.config = config or NNConfig()
        self.net = NNSeriesModel(self.config)
        self._warned: set[str] = set()

    @property
    def min_points_to_predict(self) -> int:  # type: ignore[override]
        return 2

    def update(self, obs: Observation, history: History) -> None:
        self.log.append(obs, self._one_step_error(obs, history))
        for name in self.config.channels:
            if name not in history.channels and name not in self._warned:
                self._warned.add(name)
                _log.warning("nn: channel %r not logged; its input is held at 0", name)
        t = self.log.t()
        self.net.fit(self.log.xy(), channel_matrix(history, self.config.channels, t))

    def predict(self, t_s: npt.ArrayLike, history: History) -> Prediction:
        self._require_data()
        t = as_times(t_s)
        xy = self.log.xy()
        t_last = self.log.t_s[-1]
        tail = self.log.t()[-self.config.lags - 1 :]
        inc = self.net.next_increment(
            xy[-self.config.lags - 1 :], channel_matrix(history, self.config.channels, tail)
        )
        step = self.log.step_s()
        if inc is None:
            inc = xy[-1] - xy[-2] if xy.shape[0] >= 2 else np.zeros(2)
        mean = (
            xy[-1][None, :]
            + ((t - t_last) / step if math.isfinite(step) else 0.0 * t)[:, None] * inc[None, :]
        )
        return Prediction(t, mean, self.log.horizon_sigma(t, fallback_nm=self.log.sigma_nm[-1]))

    def state_dict(self) -> dict[str, Any]:
        return {"name": self.name, "log": self.log.to_dict(), "net": self.net.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.log = ObservationLog.from_dict(state["log"])
        self.net.load_state_dict(state["net"])
        self.config = self.net.config
