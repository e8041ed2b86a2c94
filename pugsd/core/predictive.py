# SPDX-License-Identifier: Apache-2.0
"""Predictive uncertainty of the fused occupancy field: a GPyTorch SVGP (Eq. 7-8).

Eq. 7: ``SVGP(P_z) = {mu_z, sigma_z^2}``, the predictive mean and variance (latent f by default).
Eq. 8: ``sigma_pred^2 = sigma_z^2 / (1 + |mu_z|)``: dense regions get their variance divided down.

Targets are the FOF values divided by a scale ``s`` (``FofStore.compute_scale``), so the field the
GP sees is dimensionless and of order one (conditioning). Predictions are mapped back to density
units (mu s, sigma^2 s^2) before Eq. 8 by default;
``output_units = normalised`` keeps them dimensionless.

Two training schemes share one model object:
- ``fit_paper``: the paper's batch fit (Adam, lr 1e-3, 100 epochs over all points).
- ``update``: streaming: warm-started natural-gradient steps on q(u) plus Adam on
  the hyperparameters and inducing locations, minibatches mixing the newest points with a replay
  sample of the whole store, ``num_data`` equal to the store size, inducing points moved into newly
  observed regions with q(u) re-projected.
"""

from __future__ import annotations

import collections
import contextlib
import copy
import functools
import logging
import math
import threading
import weakref
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any, ParamSpec, TypeVar

import gpytorch
import numpy as np
import torch
from scipy.spatial import cKDTree

from pugsd.core.config import SvgpConfig
from pugsd.core.geometry import grid_centre
from pugsd.errors import ConfigError, EmptyCloudError, ModelNotReadyError

log = logging.getLogger(__name__)


NUM_INDUCING_AUTO_CPU = 250
ORIGIN_GRID_M = 1.0  # the model's local origin: the data's centre rounded to this grid
# the streaming model's origin follows its data once their centre is this far from it (a long
# transect: float32 at 2-4 km from the origin changed predictive variances by 5-6 %)
RECENTRE_M = 50.0
# an inducing point this many lengthscales (ARD metric) from every stored point no longer
# describes any data (kernel with every point below 1.1 % for the RBF, 2.8 % for Matern 5/2)
ORPHAN_LENGTHSCALES = 3.0
ORPHAN_FPS_POINTS = 16384  # orphaned inducing points are re-placed by FPS over at most this many points
NUM_INDUCING_AUTO_CUDA = 500


_flush_depth = threading.local()


@contextlib.contextmanager
def denormals_flushed() -> Iterator[None]:
    """Within the block the calling thread's CPU arithmetic treats denormal floats as zero (x86
    FTZ and DAZ); the mode is restored when the outermost such block ends.

    The kernel between points many lengthscales apart underflows into float32's denormal range
    (below 1.2e-38) rather than to zero, and x86 multiplies denormals in microcode: while the
    hyperparameters settle, a training step whose kernel matrices hold many of them runs several
    times slower than the same step on the same shapes later. Flushing them changes only values
    below that range. The mode is per thread and scoped to the SVGP's own training and
    prediction: code outside (open3d's normal estimation among it) has crashed under it. A no-op
    where the CPU has no such mode."""
    depth = getattr(_flush_depth, "n", 0)
    if depth == 0:
        _flush_depth.on = bool(torch.set_flush_denormal(True))
    _flush_depth.n = depth + 1
    try:
        yield
    finally:
        _flush_depth.n = depth
        if depth == 0 and _flush_depth.on:
            torch.set_flush_denormal(False)


P = ParamSpec("P")
R = TypeVar("R")


def _flushing(fn: Callable[P, R]) -> Callable[P, R]:
    """Run ``fn`` within :func:`denormals_flushed`."""

    @functools.wraps(fn)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> R:
        with denormals_flushed():
            return fn(*args, **kwargs)

    return wrapper


def local_origin(x: np.ndarray) -> np.ndarray:
    """The origin the SVGP's inputs are taken relative to: the centre of ``x`` (N, 3), rounded to
    ``ORIGIN_GRID_M`` (a map within half a metre of the world origin keeps world coordinates).

    The model runs in float32 by default, whose spacing is 1 mm at 10 km: world coordinates of a
    map far from its frame's origin (a UTM-like frame, which the point store keys relative to its
    first observation for the same reason) would put its inputs, inducing points and Algorithm 1's
    sub-millimetre sigma points on that grid (variances off by 21 % at 10 km, 175 % at 100 km).
    The shift is made in float64, before the cast."""
    return grid_centre(x, ORIGIN_GRID_M)


def resolve_num_inducing(num_inducing: int, device_type: str) -> int:
    """``svgp.num_inducing`` with 0 (auto) resolved: 250 on the CPU, where one step costs O(M^3)
    and 250 keeps a 2-core computer real-time at 10 Hz; 500 (the paper's M) on CUDA, where a step
    is launch-bound and costs what 250 costs (docs/performance.md, "On a GPU")."""
    if num_inducing > 0:
        return num_inducing
    return NUM_INDUCING_AUTO_CUDA if device_type == "cuda" else NUM_INDUCING_AUTO_CPU


def _cycle_links(modules: tuple[torch.nn.Module | None, ...], keep: tuple[torch.nn.Module, ...]) -> list[Any]:
    kept = {id(m) for k in keep for m in k.modules()}
    return [m for top in modules if top is not None for m in top.modules() if id(m) not in kept]


def release_modules(*modules: torch.nn.Module | None, keep: tuple[torch.nn.Module, ...] = ()) -> None:
    """Break the reference cycles of gpytorch modules that are being dropped, so that they (and
    their tensors) are freed as soon as the last reference goes, not when Python's cyclic
    collector next runs a full collection. Every gpytorch ``Module`` registers its own bound
    method as a ``load_state_dict`` pre-hook (module -> hook -> module), and a variational
    strategy holds its model (model -> strategy -> model), so every dropped model, likelihood,
    ELBO and prediction snapshot (with its memoised factorisations: ~1 MB at M = 250) was garbage
    that only a full (generation-2) collection frees, and in the daemon (hundreds of thousands of
    tracked objects) that comes rarely: under map resets and the grasp thread's snapshots such
    garbage piles up to hundreds of MB, and glibc keeps the heap's peak after it is freed. Only
    for modules that are dropped: a released variational strategy has no model any
    more. Submodules in ``keep`` (and theirs) are left alone: a likelihood that outlives its ELBO."""
    for m in _cycle_links(modules, keep):
        m._load_state_dict_pre_hooks.clear()
        if isinstance(m.__dict__.get("model"), torch.nn.Module):  # gpytorch's strategy -> model
            del m.__dict__["model"]


def _acyclic(model: torch.nn.Module, likelihood: torch.nn.Module) -> None:
    """Make a prediction-only copy free of reference cycles while it is in use (see
    ``release_modules``): its ``load_state_dict`` hooks go (it was loaded once and never is
    again) and its variational strategy refers to the model weakly (the model owns the strategy)."""
    for m in _cycle_links((model, likelihood), ()):
        m._load_state_dict_pre_hooks.clear()
        owner = m.__dict__.get("model")
        if isinstance(owner, torch.nn.Module):
            object.__setattr__(m, "model", weakref.proxy(owner))


def farthest_point_sample(
    points: np.ndarray, m: int, seed: int = 0, chosen: np.ndarray | None = None, kdtree: bool = False
) -> np.ndarray:
    """Indices of ``m`` farthest-point samples (greedy, O(N m)). With ``chosen`` (K, 3) points
    already in the sample, the greedy sample continues from them (the first pick is the point
    farthest from them, not a random one). ``kdtree``: the distances to ``chosen`` from a KD-tree
    (O(N log K) instead of O(N K); equal up to rounding, so ties may break differently).

    Fewer than ``min(m, N)`` indices come back when every remaining point coincides with one in
    the sample (repeated points, or ``chosen`` already on them): a repeated pick would be a
    second inducing point on the same spot, which makes K_ZZ singular."""
    n = len(points)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    m = min(m, n)
    idx = np.empty(m, dtype=np.int64)
    if m == 0:
        return idx
    if chosen is not None and len(chosen) and kdtree:
        d2 = cKDTree(np.asarray(chosen, dtype=np.float64)).query(points)[0] ** 2
        start = 0
    elif chosen is not None and len(chosen):
        d2 = np.full(n, np.inf)
        for c in np.asarray(chosen, dtype=np.float64):
            d2 = np.minimum(d2, ((points - c) ** 2).sum(1))
        start = 0
    else:
        idx[0] = np.random.default_rng(seed).integers(n)
        d2 = ((points - points[idx[0]]) ** 2).sum(1)
        start = 1
    for i in range(start, m):
        j = int(np.argmax(d2))
        if d2[j] <= 0.0:  # every point is in the sample already
            return idx[:i]
        idx[i] = j
        d2 = np.minimum(d2, ((points - points[j]) ** 2).sum(1))
    return idx


class _SVGP(gpytorch.models.ApproximateGP):  # type: ignore[misc]
    def __init__(self, Z: torch.Tensor, natural: bool, kernel: str, lengthscale: float) -> None:
        m = Z.shape[0]
        vd: gpytorch.variational._VariationalDistribution
        if natural:
            vd = gpytorch.variational.NaturalVariationalDistribution(m)
        else:
            vd = gpytorch.variational.CholeskyVariationalDistribution(m)
        vs = gpytorch.variational.VariationalStrategy(self, Z, vd, learn_inducing_locations=True)
        super().__init__(vs)
        # zero prior mean: the occupancy density vanishes away from observed surfaces
        self.mean_module = gpytorch.means.ZeroMean()
        base: gpytorch.kernels.Kernel
        if kernel == "matern52":
            base = gpytorch.kernels.MaternKernel(nu=2.5, ard_num_dims=3)
        else:
            base = gpytorch.kernels.RBFKernel(ard_num_dims=3)
        base.lengthscale = lengthscale
        self.covar_module = gpytorch.kernels.ScaleKernel(base)

    def forward(self, x: torch.Tensor) -> gpytorch.distributions.MultivariateNormal:
        return gpytorch.distributions.MultivariateNormal(self.mean_module(x), self.covar_module(x))


@dataclass(frozen=True)
class TrainStats:
    steps: int
    elbo: float
    ready: bool
    inducing_moved: int
    num_data: int


class OccupancySVGP:
    """The SVGP on the FOF targets, with batch (paper) and streaming training."""

    def __init__(self, cfg: SvgpConfig, natural: bool | None = None) -> None:
        self.cfg = cfg
        if cfg.device == "auto":
            self.device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
        else:
            self.device = torch.device(cfg.device)
        if self.device.type == "cuda" and not torch.cuda.is_available():
            raise ConfigError(f"svgp.device = {cfg.device}, but torch sees no CUDA device")
        self.num_inducing = resolve_num_inducing(cfg.num_inducing, self.device.type)
        self.dtype = torch.float64 if cfg.dtype == "float64" else torch.float32
        self.natural = cfg.natural_gradient if natural is None else natural
        self._gen = torch.Generator().manual_seed(cfg.seed)
        self._rng = np.random.default_rng(cfg.seed)
        self.model: _SVGP | None = None
        self.likelihood: gpytorch.likelihoods.GaussianLikelihood | None = None
        # inputs are modelled relative to this point (``local_origin``), set when a model is created;
        # inducing points are stored in these local coordinates
        self.origin = np.zeros(3)
        self.total_steps = 0
        self.steps_since_init = 0
        self._moves: collections.deque[tuple[int, int]] = collections.deque()  # (step, points moved)
        self._elbos: collections.deque[float] = collections.deque(maxlen=2 * cfg.ready_elbo_window)
        self.last_elbo = float("nan")
        self.version = 0
        self._ngd: gpytorch.optim.NGD | None = None
        self._adam: torch.optim.Optimizer | None = None
        self._mll: gpytorch.mlls.VariationalELBO | None = None
        self._good_state: tuple[dict[str, Any], dict[str, Any]] | None = None
        # streaming: a factor on every learning rate (``set_rate_scale``; the daemon lowers it in
        # idle training so that the model settles instead of jittering with its minibatches)
        self._rate_scale = 1.0
        self.failures = 0
        self.consecutive_failures = 0

    # ------------------------------------------------------------------ set-up
    def _t(self, a: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(a, dtype=self.dtype, device=self.device)

    def _local(self, x: np.ndarray) -> np.ndarray:
        """World points (N, 3) in the model's local coordinates (float64 subtraction)."""
        return np.asarray(x, dtype=np.float64) - self.origin

    def _recentre(self, centre: np.ndarray) -> None:
        """Move the model's origin to ``centre`` when the data has moved ``RECENTRE_M`` or more
        from it along some axis (the point store forgets the oldest voxels, so a vehicle on a long
        transect keeps a map far from where it began). The inducing points are shifted by the same
        amount in float64; the kernel is stationary and q(u) is whitened, so the model is the same
        function of world coordinates, kept in float32 near zero."""
        d = np.asarray(centre, dtype=np.float64) - self.origin
        if self.model is None or float(np.abs(d).max()) < RECENTRE_M:
            return
        vs = self.model.variational_strategy
        with torch.no_grad():
            Z = vs.inducing_points
            shift = torch.as_tensor(d, dtype=torch.float64, device=Z.device)
            Z.copy_((Z.double() - shift).to(Z.dtype))
        vs._memoize_cache = {}
        self.origin = np.asarray(centre, dtype=np.float64)
        self._save_good_state()  # a later failure restores a state in these coordinates
        self.version += 1
        log.info("SVGP origin moved by %.0f m (the map moved): inducing points shifted", np.linalg.norm(d))

    def _init_model(self, x: np.ndarray, y: np.ndarray, num_inducing: int | None = None) -> None:
        m = self.num_inducing if num_inducing is None else num_inducing
        zi = farthest_point_sample(x, m, self.cfg.seed)
        Z = self._t(x[zi])
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(self.cfg.seed)  # q(u) is initialised with random noise
            model = _SVGP(Z, self.natural, self.cfg.kernel, self.cfg.lengthscale_init_m)
            model.variational_strategy._variational_distribution.initialize_variational_distribution(
                model.variational_strategy.prior_distribution
            )
            # else gpytorch initialises q(u) again at the first training call, from the global
            # torch RNG, and the seed no longer fixes the fit
            model.variational_strategy.variational_params_initialized.fill_(1)
        lik = gpytorch.likelihoods.GaussianLikelihood()
        lik.noise = self.cfg.noise_init
        self._release_model()
        self.model = model.to(device=self.device, dtype=self.dtype)
        self.likelihood = lik.to(device=self.device, dtype=self.dtype)
        self._mll = gpytorch.mlls.VariationalELBO(self.likelihood, self.model, num_data=len(x))
        self._make_optimizers(len(x))
        self.steps_since_init = 0
        self._moves.clear()
        self._elbos.clear()
        self.version += 1
        self._save_good_state()

    def _make_optimizers(self, num_data: int) -> None:
        assert self.model is not None and self.likelihood is not None
        hyper = [p for n, p in self.model.named_parameters() if "variational_strategy" not in n]
        hyper += list(self.likelihood.parameters())
        if self.natural:
            self._ngd = gpytorch.optim.NGD(
                self.model.variational_parameters(), num_data=num_data, lr=self.cfg.ngd_lr
            )
            self._ngd.param_groups[0]["base_lr"] = self.cfg.ngd_lr
            groups = [{"params": hyper, "lr": self.cfg.adam_lr, "base_lr": self.cfg.adam_lr}]
            if self.cfg.inducing_lr > 0:
                groups.append(
                    {
                        "params": [self.model.variational_strategy.inducing_points],
                        "lr": self.cfg.inducing_lr,
                        "base_lr": self.cfg.inducing_lr,
                    }
                )
            self._adam = torch.optim.Adam(groups)
        else:
            self._ngd = None
            self._adam = torch.optim.Adam(
                [*self.model.parameters(), *self.likelihood.parameters()], lr=self.cfg.paper_lr
            )
            self._adam.param_groups[0]["base_lr"] = self.cfg.paper_lr
        self._apply_rate_scale()

    @property
    def rate_scale(self) -> float:
        return self._rate_scale

    def set_rate_scale(self, scale: float) -> None:
        """Multiply the streaming learning rates (``ngd_lr``, ``adam_lr``, ``inducing_lr``) by
        ``scale`` in (0, 1] from the next step on, also for optimizers made later (a model that
        grows or recovers). 1 restores the configured rates, as ``reset`` does; ``fit_paper``
        always runs at the paper's rate.

        A minibatch step at a constant rate keeps the model jittering about its optimum:
        sigma^2_occ moves by several percent from one grasp round to the next, so near-tied grasps
        swap ranks each time the daemon republishes them. Decaying rates (Robbins-Monro) let it
        settle."""
        if not (math.isfinite(scale) and 0.0 < scale <= 1.0):
            raise ValueError(f"rate scale must be in (0, 1], got {scale}")
        if scale != self._rate_scale:
            self._rate_scale = float(scale)
            self._apply_rate_scale()

    def _apply_rate_scale(self) -> None:
        for opt in (self._ngd, self._adam):
            if opt is not None:
                for group in opt.param_groups:
                    group["lr"] = group["base_lr"] * self._rate_scale

    def state(self) -> tuple[dict[str, Any], dict[str, Any]]:
        """A copy of the model's and the likelihood's parameters (``load_state`` puts it back)."""
        assert self.model is not None and self.likelihood is not None
        return (
            copy.deepcopy(self.model.state_dict()),
            copy.deepcopy(self.likelihood.state_dict()),
        )

    def load_state(self, state: tuple[dict[str, Any], dict[str, Any]]) -> None:
        """Restore parameters taken by ``state`` (same inducing count; inducing points are in
        the local coordinates of ``origin``, so from this model or one with the same origin),
        dropping gpytorch's memoised factorisations of the old ones."""
        assert self.model is not None and self.likelihood is not None
        self.model.load_state_dict(state[0])
        self.likelihood.load_state_dict(state[1])
        self.model.variational_strategy._memoize_cache = {}
        self.version += 1

    def _save_good_state(self) -> None:
        self._good_state = self.state()

    def _recover(self, exc: Exception, n: int) -> None:
        """A numerical failure (e.g. NotPSDError) must not poison later steps: restore the last
        good state with fresh optimizers; after 3 failures in a row start a fresh model."""
        assert self.model is not None and self.likelihood is not None
        self.failures += 1
        self.consecutive_failures += 1
        log.warning("SVGP step failed (%s: %s); restoring the last good state", type(exc).__name__, exc)
        if self._good_state is not None:
            self.load_state(self._good_state)
        self._make_optimizers(n)

    @property
    def initialised(self) -> bool:
        return self.model is not None

    def _release_model(self) -> None:
        """Drop the model, likelihood, ELBO and optimizers (``release_modules``: freed now, not by
        a later full collection)."""
        release_modules(self.model, self.likelihood, self._mll)
        self.model = None
        self.likelihood = None
        self._mll = None
        self._ngd = None
        self._adam = None
        self._good_state = None

    def reset(self) -> None:
        self._release_model()
        self._rate_scale = 1.0
        self.total_steps = 0
        self._elbos.clear()
        self.version += 1

    # ------------------------------------------------------------------ training
    def _step(self, xb: torch.Tensor, yb: torch.Tensor) -> float:
        assert self.model is not None and self._mll is not None and self._adam is not None
        self.model.train()
        assert self.likelihood is not None
        self.likelihood.train()
        if self._ngd is not None:
            self._ngd.zero_grad()
        self._adam.zero_grad()
        out = self.model(xb)
        loss = -self._mll(out, yb)
        loss.backward()
        if self._ngd is not None:
            self._ngd.step()
        self._adam.step()
        self.total_steps += 1
        self.steps_since_init += 1
        elbo = -float(loss.detach())
        self.last_elbo = elbo
        self._elbos.append(elbo)
        return elbo

    @_flushing
    def fit_paper(self, x: np.ndarray, y: np.ndarray, epochs: int | None = None) -> TrainStats:
        """The paper's batch fit: a fresh model with ``paper_num_inducing`` inducing points (FPS),
        Adam (lr ``paper_lr``), ``paper_epochs`` epochs."""
        if len(x) == 0:
            raise EmptyCloudError("no training points")
        self.natural = False
        self.reset()
        self.origin = local_origin(x)
        x = self._local(x)
        self._init_model(x, y, self.cfg.paper_num_inducing)
        xt, yt = self._t(x), self._t(y)
        n = len(x)
        bs = self.cfg.batch_size
        epochs = self.cfg.paper_epochs if epochs is None else epochs
        elbo = float("nan")
        for _ in range(epochs):
            perm = torch.randperm(n, generator=self._gen)
            for i in range(0, n, bs):
                sel = perm[i : i + bs].to(self.device)
                elbo = self._step(xt[sel], yt[sel])
        self.version += 1
        return TrainStats(self.total_steps, elbo, True, 0, n)

    @_flushing
    def update(
        self, x: np.ndarray, y: np.ndarray, new_idx: np.ndarray, steps: int | None = None
    ) -> TrainStats:
        """Streaming update on the whole store ``(x, y)`` after ``new_idx`` changed (Sec. 5.3)."""
        n = len(x)
        if n == 0:
            raise EmptyCloudError("no training points")
        if self.model is None:
            self.origin = local_origin(x)
        else:
            self._recentre(local_origin(x))
        x = self._local(x)
        moved = 0
        if self.model is None:
            self.natural = self.cfg.natural_gradient
            self._init_model(x, y)
        else:
            try:
                moved = self._grow_inducing(x) + self._cover_new_region(x, new_idx)
            except (RuntimeError, ValueError) as exc:  # NotPSDError while re-projecting q(u)
                self._recover(exc, n)
                self._fresh_after_failures(x, y)
                return TrainStats(self.total_steps, float("nan"), False, 0, n)
        assert self._mll is not None
        self._mll.num_data = n
        if self._ngd is not None:
            # gpytorch's NGD scales its step by its own ``num_data`` attribute (not a param-group
            # key): it must follow the store, or the natural-gradient rate shrinks as N0 / N
            self._ngd.num_data = n
        xt, yt = self._t(x), self._t(y)
        bs = min(self.cfg.batch_size, n)
        n_new = round(bs * (1.0 - self.cfg.replay_fraction)) if len(new_idx) else 0
        elbo = float("nan")
        steps = self.cfg.steps_per_update if steps is None else steps
        for _ in range(steps):
            parts = []
            if n_new > 0:
                parts.append(self._rng.choice(new_idx, size=min(n_new, len(new_idx)), replace=False))
            parts.append(self._rng.choice(n, size=bs - sum(len(p) for p in parts), replace=False))
            sel = torch.as_tensor(np.concatenate(parts), device=self.device)
            try:
                elbo = self._step(xt[sel], yt[sel])
            except (RuntimeError, ValueError) as exc:  # NotPSDError is a RuntimeError
                self._recover(exc, n)
                self._fresh_after_failures(x, y)
                return TrainStats(self.total_steps, float("nan"), False, moved, n)
            if not np.isfinite(elbo):
                self._recover(FloatingPointError("non-finite ELBO"), n)
                return TrainStats(self.total_steps, float("nan"), False, moved, n)
        self.consecutive_failures = 0
        self._save_good_state()
        self.version += 1
        return TrainStats(self.total_steps, elbo, self.is_ready(), moved, n)

    def _fresh_after_failures(self, x: np.ndarray, y: np.ndarray) -> None:
        """After 3 failures in a row (training steps or inducing-point moves) start a fresh model:
        a failure that the last good state reproduces would otherwise stop training for good."""
        if self.consecutive_failures >= 3:
            log.warning("SVGP failed 3 times in a row: starting a fresh model")
            self._init_model(x, y)
            self.consecutive_failures = 0

    def moved_recently(self) -> int:
        """Inducing points moved within the last ``ready_move_window`` steps."""
        horizon = self.total_steps - self.cfg.ready_move_window
        while self._moves and self._moves[0][0] < horizon:
            self._moves.popleft()
        return sum(k for _, k in self._moves)

    def elbo_slope(self) -> float | None:
        """Change of the minibatch ELBO per point and per step: the mean of the last
        ``ready_elbo_window`` steps minus the mean of the window before, over the window length.
        None until the model has had two windows of steps since it was created."""
        w = self.cfg.ready_elbo_window
        if len(self._elbos) < 2 * w:
            return None
        e = np.fromiter(self._elbos, dtype=np.float64, count=2 * w)
        return float(e[w:].mean() - e[:w].mean()) / w

    def is_ready(self) -> bool:
        """Ready once the model has had ``ready_min_steps`` steps since it was created, at most
        ``ready_max_moved_fraction`` of the inducing points moved within the last
        ``ready_move_window`` steps, and the ELBO per point changes by less than
        ``ready_elbo_slope`` nats per step (``elbo_slope``; or 4 x ``ready_min_steps`` steps
        passed).

        The ELBO test is absolute, in nats per point: a relative change is ill-posed near an ELBO
        of 0, where a well-fitted model lives. It compares two windows of raw minibatch ELBOs, so
        the first steps after the model is created (q(u) at its prior) weigh only until they
        leave the window.

        A few inducing points moved into a new view do not reset readiness: the move re-projects
        q(u) so that the posterior at the new inducing points is kept (the field changes only
        near the points that moved); what is not yet fitted is the new data, as after any new
        frame. Many moves at once (a new object, a large unseen region) do."""
        if self.model is None:
            return False
        n = self.cfg.ready_min_steps
        if self.steps_since_init < n:
            return False
        m = len(self.model.variational_strategy.inducing_points)
        if self.moved_recently() > self.cfg.ready_max_moved_fraction * m:
            return False
        if self.steps_since_init >= 4 * n:
            return True
        slope = self.elbo_slope()
        return slope is not None and abs(slope) < self.cfg.ready_elbo_slope

    def _grow_inducing(self, x: np.ndarray) -> int:
        """Add inducing points while the model has fewer than ``min(M, N)``: the model was created
        on a store smaller than M (a first frame that saw little, the first one after a reset) and
        would otherwise keep that count for good.

        The new points continue the farthest-point sample of the store from the current inducing
        points; the model is rebuilt with the same hyperparameters and q(u) re-projected onto the
        larger set (``_whitened_posterior_at``), so the posterior does not jump; the optimizers
        start afresh (their parameters changed shape). Returns the number of points added."""
        assert self.model is not None and self.likelihood is not None
        vs = self.model.variational_strategy
        Z = vs.inducing_points.detach()
        m_old = len(Z)
        m_target = min(self.num_inducing, len(x))
        if m_old >= m_target:
            return 0
        add = farthest_point_sample(x, m_target - m_old, chosen=Z.double().cpu().numpy())
        if len(add) == 0:  # the store's points all hold an inducing point (repeated points)
            return 0
        m_target = m_old + len(add)
        with torch.no_grad():
            Z_new = torch.cat([Z, self._t(x[add])])
            m_w, S_w = self._whitened_posterior_at(Z_new)
            model = _SVGP(Z_new, self.natural, self.cfg.kernel, self.cfg.lengthscale_init_m)
            model = model.to(device=self.device, dtype=self.dtype)
            model.covar_module.load_state_dict(self.model.covar_module.state_dict())
            model.variational_strategy.variational_params_initialized.fill_(1)
        release_modules(self.model, self._mll, keep=(self.likelihood,))
        self.model = model
        self._write_whitened_q(m_w, S_w)
        self._mll = gpytorch.mlls.VariationalELBO(self.likelihood, self.model, num_data=len(x))
        self._make_optimizers(len(x))
        self._save_good_state()  # a later failure restores this model, not one of the old size
        self.version += 1
        self._moves.append((self.total_steps, m_target - m_old))
        log.info("SVGP: %d inducing points added (%d of %d)", m_target - m_old, m_target, self.num_inducing)
        return m_target - m_old

    def _cover_new_region(self, x: np.ndarray, new_idx: np.ndarray) -> int:
        """Swap inducing points into newly observed regions and re-project q(u) (Sec. 5.1).

        New points farther than ``coverage_lengthscales`` lengthscales (Mahalanobis in the ARD
        metric) from every inducing point are covered by FPS samples, replacing the inducing
        points with the least posterior influence (smallest |m| of the whitened mean). The
        variational distribution is re-projected so that the posterior at the new inducing points
        is kept at the moment of the swap: m = mu_f(Z_new), S = Sigma_f(Z_new), whitened with the
        new Cholesky factor (``_reproject``).
        """
        assert self.model is not None
        if len(new_idx) == 0:
            return 0
        if self.cfg.inducing_policy == "spread":
            return self._spread_inducing(x, new_idx)
        vs = self.model.variational_strategy
        Z = vs.inducing_points.detach()
        ls = self.model.covar_module.base_kernel.lengthscale.detach().reshape(1, 3)
        xn = self._t(x[new_idx])
        d = torch.cdist(xn / ls, Z / ls).min(dim=1).values
        far = (d > self.cfg.coverage_lengthscales).cpu().numpy()
        if not far.any():
            return 0
        cand = x[new_idx][far]
        k = int(min(len(cand), max(1, 0.3 * len(Z)), max(1, math.ceil(len(cand) / 20))))
        pick = cand[farthest_point_sample(cand, k, self.cfg.seed + self.total_steps)]
        k = len(pick)  # fewer where candidates repeat a point
        with torch.no_grad():
            m_white = self._whitened_mean()
            influence = m_white.abs()
            replace = torch.argsort(influence)[:k]
            Z_new = Z.clone()
            Z_new[replace] = self._t(pick)
            self._reproject(Z_new)
        self._moves.append((self.total_steps, k))
        return k

    def _orphans(self, x: np.ndarray, Z: np.ndarray) -> np.ndarray:
        """Inducing points (M,) that no longer describe any stored point: farther than
        ``ORPHAN_LENGTHSCALES`` from every point of ``x``, in the ARD metric (each axis in its
        own lengthscale).

        The point store forgets its oldest voxels (``fof.max_voxels``), so on a transect the
        inducing points placed on the first metres end up with no data near them. Kept, they hold
        the model's capacity (7 of 250 inducing points on the last 2 m of a 100 m transect) and
        stretch the inducing set over the whole transect, where float32 kernel distances (gpytorch
        expands |a - b|^2 about the set's mean) lose their precision. A survey leg that turns
        back forgets ground inside the extent of what the store still holds, so the test is the
        distance to the nearest stored point, not to their bounding box.

        Exact and cheap: a KD-tree over a strided subsample (at most ``ORPHAN_FPS_POINTS``)
        clears every inducing point within the distance of a subsample point; only the rest (an
        inducing point on a patch too small for the stride to sample, or a true orphan) are
        measured against every stored point: by products for a few candidates, by a KD-tree over
        the store for more (products for all M would cost several times more). An inducing point
        placed on a stored point is at
        distance 0 while the store keeps that point."""
        assert self.model is not None
        ls = self.model.covar_module.base_kernel.lengthscale.detach().double().cpu().numpy().reshape(3)
        xs, Zs = x / ls, Z / ls
        sub = xs[:: max(1, -(-len(xs) // ORPHAN_FPS_POINTS))]
        far = cKDTree(sub).query(Zs, distance_upper_bound=ORPHAN_LENGTHSCALES)[0] > ORPHAN_LENGTHSCALES
        idx = np.flatnonzero(far)
        if idx.size > 16:  # many (a store that moved on): one KD-tree over every stored point
            far[idx] = cKDTree(xs).query(Zs[idx], distance_upper_bound=ORPHAN_LENGTHSCALES)[0] > (
                ORPHAN_LENGTHSCALES
            )
        elif idx.size:
            # a few (an inducing point on a patch the stride missed): the squared distances to every
            # stored point by one product, exact in float64 for local coordinates (|x| / lengthscale
            # up to ~1e4 against a threshold of 9)
            Zc = Zs[idx]
            d2 = np.full(idx.size, np.inf)
            x2 = (xs**2).sum(1)
            for lo in range(0, len(xs), 65536):
                blk = slice(lo, lo + 65536)
                part = x2[blk, None] - 2.0 * xs[blk] @ Zc.T + (Zc**2).sum(1)[None, :]
                d2 = np.minimum(d2, part.min(0))
            far[idx] = d2 > ORPHAN_LENGTHSCALES**2
        return far

    def _spread_inducing(self, x: np.ndarray, new_idx: np.ndarray) -> int:
        """Keep the inducing points spread like a farthest-point sample of everything observed
        (what the paper's batch fit starts from), incrementally (Sec. 5.1).

        Inducing points that no longer describe any stored point (``_orphans``: the store forgot
        their data) are placed first, continuing the farthest-point sample of the store (a strided
        subsample of at most ``ORPHAN_FPS_POINTS``) from the other inducing points. Then the
        spacing is the median nearest-neighbour distance among the inducing points; new points
        farther than ``spread_factor`` spacings from every inducing point are covered greedily
        (farthest first, at most 30 % of M per update); each one takes the place of the most
        crowded inducing point (the smallest nearest-neighbour distance). q(u) is re-projected
        once for all the moves."""
        assert self.model is not None
        vs = self.model.variational_strategy
        Z = vs.inducing_points.detach().double().cpu().numpy()
        m = len(Z)
        orphans = np.flatnonzero(self._orphans(x, Z))
        fresh = np.zeros(m, dtype=bool)  # placed in this update: not removed again
        k = 0
        if orphans.size:
            sub = x[:: max(1, -(-len(x) // ORPHAN_FPS_POINTS))]
            keep = np.ones(m, dtype=bool)
            keep[orphans] = False
            pick = farthest_point_sample(sub, orphans.size, self.cfg.seed, chosen=Z[keep], kdtree=True)
            # a store with fewer points than orphans (a caller's store that shrank; pugsd's only
            # grows until fof.max_voxels): the rest stay where they are until points come
            placed = orphans[: len(pick)]
            Z[placed] = sub[pick]
            fresh[placed] = True
            k = len(placed)
            if k:
                log.info("SVGP: %d inducing points without data near them (the store forgot it) re-placed", k)
        D = np.sqrt(((Z[:, None, :] - Z[None, :, :]) ** 2).sum(-1))
        np.fill_diagonal(D, np.inf)
        thresh = self.cfg.spread_factor * float(np.median(D.min(1)))
        cand = x[new_idx]
        dc = cKDTree(Z).query(cand)[0]  # distance to the nearest inducing point (no (n, M, 3) temporary)
        budget = max(1, int(0.3 * m))
        while budget > 0 and not fresh.all():
            j = int(np.argmax(dc))
            if dc[j] <= thresh:
                break
            nn = np.where(fresh, np.inf, D.min(1))
            r = int(np.argmin(nn))
            Z[r] = cand[j]
            fresh[r] = True
            d_r = np.sqrt(((Z - Z[r]) ** 2).sum(1))
            d_r[r] = np.inf
            D[r, :] = d_r
            D[:, r] = d_r
            dc = np.minimum(dc, np.sqrt(((cand - cand[j]) ** 2).sum(1)))
            k += 1
            budget -= 1
        if k == 0:
            return 0
        with torch.no_grad():
            self._reproject(self._t(Z))
        self._moves.append((self.total_steps, k))
        return k

    def _whitened_mean(self) -> torch.Tensor:
        assert self.model is not None
        vd = self.model.variational_strategy._variational_distribution
        return vd().mean.detach()

    def _whitened_q64(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The whitened q(v) = N(m_w, S_w) in float64, from the distribution's own parameters."""
        assert self.model is not None
        vd = self.model.variational_strategy._variational_distribution
        f64 = torch.float64
        if isinstance(vd, gpytorch.variational.NaturalVariationalDistribution):
            P = -2.0 * vd.natural_mat.detach().to(f64)  # natural_mat = -S^-1 / 2
            P = 0.5 * (P + P.mT)
            S = torch.cholesky_inverse(torch.linalg.cholesky(P))
            return S @ vd.natural_vec.detach().to(f64), 0.5 * (S + S.mT)
        L_S = vd.chol_variational_covar.detach().to(f64).tril()
        return vd.variational_mean.detach().to(f64), L_S @ L_S.mT

    def _reproject(self, Z_new: torch.Tensor) -> None:
        """Write q(u) for new inducing points ``Z_new`` as the current posterior of their
        inducing variables (Sec. 5.1): ``q(u_new) = int p(u_new | u) q(u) du``.

        gpytorch's inducing variables are ``u = f(Z) + e`` with the strategy's jitter ``j`` as a
        nugget ``e`` (``K_ZZ + j I = L L^T``). With a nugget per location, an inducing point that
        does not move keeps its own: ``C = cov(u, u_new) = K(Z, Z_new) + j [Z_i = Z_new,k]``,
        ``A = C^T L^-T``, mean ``A m_w``, covariance ``K_nn + j I - A A^T + A S_w A^T``, whitened
        with the new factor. Onto the same Z this is the identity (exactly, up to float32
        storage); the points that stay keep their marginal; where points moved, predictions
        nearby change (the old points no longer pin them).

        Float64 throughout (float32 algebra, without the nugget, changed predictive variances by
        ~10 % on an identity re-projection). The prior mean is zero (``_SVGP``)."""
        m_new, S_new = self._whitened_posterior_at(Z_new)
        assert self.model is not None
        self.model.variational_strategy.inducing_points.data.copy_(Z_new)
        self._write_whitened_q(m_new, S_new)  # also drops the cached factors of Kzz (Z changed)

    def _whitened_posterior_at(self, Z_new: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The whitened q(v_new) = N(m, S) that ``_reproject`` writes for ``Z_new`` (any count)."""
        assert self.model is not None
        model = self.model
        vs = model.variational_strategy
        f64 = torch.float64
        jitter = float(vs.jitter_val)
        with torch.no_grad():
            kern = copy.deepcopy(model.covar_module).to(f64)
            Z_old = vs.inducing_points.detach().to(f64)
            Z_n = Z_new.detach().to(f64)
            eye_old = torch.eye(len(Z_old), dtype=f64, device=Z_old.device)
            eye_new = torch.eye(len(Z_n), dtype=f64, device=Z_n.device)
            m_w, S_w = self._whitened_q64()
            L_old = torch.linalg.cholesky(kern(Z_old).to_dense() + jitter * eye_old)
            # u = f(Z) + a jitter nugget per location: an inducing point that stays keeps its own
            same = (Z_old[:, None, :] == Z_n[None, :, :]).all(-1).to(f64)
            C = kern(Z_old, Z_n).to_dense() + jitter * same  # cov(u_old, u_new)
            A = torch.linalg.solve_triangular(L_old, C, upper=False).mT
            Kj_new = kern(Z_n).to_dense() + jitter * eye_new
            mean = A @ m_w
            cov = Kj_new - A @ A.mT + A @ S_w @ A.mT
            L_new = torch.linalg.cholesky(Kj_new)
            m_new = torch.linalg.solve_triangular(L_new, mean.unsqueeze(-1), upper=False).squeeze(-1)
            tmp = torch.linalg.solve_triangular(L_new, cov, upper=False)
            S_new = torch.linalg.solve_triangular(L_new, tmp.mT, upper=False).mT
            S_new = 0.5 * (S_new + S_new.mT) + 1e-10 * eye_new
        release_modules(kern)  # a float64 copy for this call only
        return m_new, S_new

    def _write_whitened_q(
        self, m_w: torch.Tensor, S_w: torch.Tensor, S_inv: torch.Tensor | None = None
    ) -> None:
        """Write the whitened q(v) = N(m_w, S_w) into the variational distribution, in its own
        parametrisation (natural: S^-1 m and -S^-1 / 2; else mean and Cholesky factor), and drop
        the strategy's memoised factors. ``S_inv``: S_w^-1 where the caller has it."""
        assert self.model is not None
        vs = self.model.variational_strategy
        vd = vs._variational_distribution
        with torch.no_grad():
            if isinstance(vd, gpytorch.variational.NaturalVariationalDistribution):
                P = torch.linalg.inv(S_w) if S_inv is None else S_inv
                vd.natural_vec.data.copy_((P @ m_w).to(self.dtype))
                vd.natural_mat.data.copy_((-0.5 * P).to(self.dtype))
            else:
                vd.variational_mean.data.copy_(m_w.to(self.dtype))
                vd.chol_variational_covar.data.copy_(torch.linalg.cholesky(S_w).to(self.dtype))
        vs._memoize_cache = {}

    @_flushing
    def set_optimal_q(self, x: np.ndarray, y: np.ndarray, chunk: int = 4096) -> float:
        """Set q(u) to its exact optimum given the current hyperparameters, inducing points Z and
        all the data ``(x, y)`` (Titsias 2009; what full-batch NGD with lr 1 reaches in one step).

        Whitened, u = L v with L L^T = K_ZZ (+ the strategy's jitter), A = L^-1 K_ZX:
        S = (I + A A^T / sigma_n^2)^-1 and m = S A y / sigma_n^2 maximise the ELBO over q(v).
        Used as a converged reference (benchmark): the batch fit's Adam leaves q(u) far from it.
        Returns the full-data ELBO per point afterwards. Float64 inside; O(N M^2 + M^3)."""
        if self.model is None or self.likelihood is None:
            raise ModelNotReadyError("the SVGP has not been trained")
        if len(x) == 0:
            raise EmptyCloudError("no training points")
        x_W, x = x, self._local(x)
        model = self.model
        vs = model.variational_strategy
        f64 = torch.float64
        with torch.no_grad():
            Z = vs.inducing_points.detach()
            kern = model.covar_module
            m = len(Z)
            eye = torch.eye(m, dtype=f64, device=Z.device)
            Kzz = kern(Z).to_dense().to(f64) + float(vs.jitter_val) * eye
            L = torch.linalg.cholesky(Kzz)
            AAt = torch.zeros(m, m, dtype=f64, device=Z.device)
            Ay = torch.zeros(m, dtype=f64, device=Z.device)
            for i in range(0, len(x), chunk):
                xb = self._t(x[i : i + chunk])
                yb = torch.as_tensor(y[i : i + chunk], dtype=f64, device=Z.device)
                A = torch.linalg.solve_triangular(L, kern(Z, xb).to_dense().to(f64), upper=False)
                AAt += A @ A.mT
                Ay += A @ (yb - model.mean_module(xb).to(f64))
            noise = float(self.likelihood.noise.detach().to(f64).reshape(-1)[0])
            prec = eye + AAt / noise  # S^-1
            S = torch.cholesky_inverse(torch.linalg.cholesky(prec))
            S = 0.5 * (S + S.mT)
            self._write_whitened_q(S @ Ay / noise, S, prec)
        self.version += 1
        return self.elbo_per_point(x_W, y, chunk)

    @_flushing
    def elbo_per_point(self, x: np.ndarray, y: np.ndarray, chunk: int = 4096) -> float:
        """The ELBO of the current model on all of ``(x, y)``, per point (full data, no minibatch
        noise): (sum of expected log-likelihoods - KL(q(u) || p(u))) / N."""
        if self.model is None or self.likelihood is None:
            raise ModelNotReadyError("the SVGP has not been trained")
        n = len(x)
        x = self._local(x)
        mll = gpytorch.mlls.VariationalELBO(self.likelihood, self.model, num_data=n)
        self.model.train()
        self.likelihood.train()
        total = 0.0
        with torch.no_grad():
            for i in range(0, n, chunk):
                xb, yb = self._t(x[i : i + chunk]), self._t(y[i : i + chunk])
                # each chunk's value is sum(ell_b) / B - KL / N; weighted by B they sum to the ELBO
                total += float(mll(self.model(xb), yb)) * len(xb)
        self.model.variational_strategy._memoize_cache = {}
        return total / n

    # ------------------------------------------------------------------ prediction
    def predict(self, x: np.ndarray, scale: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Eq. 7-8 at points x (N, 3): (mu_z, sigma_z^2, sigma_pred^2).

        The model predicts in normalised units; ``scale`` maps back (mu s, sigma^2 s^2) before
        Eq. 8 (``output_units = density``; pass 1 for the normalised units)."""
        if self.model is None or self.likelihood is None:
            raise ModelNotReadyError("the SVGP has not been trained")
        return _predict(self.model, self.likelihood, self.cfg, self._t, self._local(x), scale)

    def snapshot(self) -> SvgpSnapshot:
        """A frozen copy of the current model for prediction on another thread while this one
        trains on (a few ms for M = 250). Predictions equal ``predict`` at the time of the copy."""
        if self.model is None or self.likelihood is None:
            raise ModelNotReadyError("the SVGP has not been trained")
        # a fresh module loaded from the state dict: deepcopy of a trained model fails on the
        # non-leaf tensors that gpytorch memoises
        Z = self.model.variational_strategy.inducing_points.detach().clone()
        with torch.random.fork_rng(devices=[]):
            model = _SVGP(Z, self.natural, self.cfg.kernel, self.cfg.lengthscale_init_m)
        model = model.to(device=self.device, dtype=self.dtype)
        model.load_state_dict(self.model.state_dict())
        lik = gpytorch.likelihoods.GaussianLikelihood().to(device=self.device, dtype=self.dtype)
        lik.load_state_dict(self.likelihood.state_dict())
        _acyclic(model, lik)  # freed when the grasp thread drops it (one a second), not by a full gc
        return SvgpSnapshot(model, lik, self.cfg, self._t, self.origin.copy())


class SvgpSnapshot:
    """A frozen copy of an ``OccupancySVGP`` model that can only predict (``OccupancySVGP.snapshot``)."""

    def __init__(
        self,
        model: _SVGP,
        likelihood: gpytorch.likelihoods.GaussianLikelihood,
        cfg: SvgpConfig,
        to_tensor: Any,
        origin: np.ndarray | None = None,
    ) -> None:
        self._model, self._likelihood, self._cfg, self._t = model, likelihood, cfg, to_tensor
        self._origin = None if origin is None else np.asarray(origin, dtype=np.float64)

    def predict(self, x: np.ndarray, scale: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Eq. 7-8, as ``OccupancySVGP.predict`` (world points, taken relative to the model's
        local origin; None: the model's inputs are taken as they are)."""
        x_local = x if self._origin is None else np.asarray(x, dtype=np.float64) - self._origin
        return _predict(self._model, self._likelihood, self._cfg, self._t, x_local, scale)


@_flushing
def _predict(
    model: _SVGP,
    likelihood: gpytorch.likelihoods.GaussianLikelihood,
    cfg: SvgpConfig,
    to_tensor: Any,
    x: np.ndarray,
    scale: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eq. 7 (latent or observed predictive mean and variance, chunked), mapped to ``scale``
    units, and Eq. 8: ``sigma_pred^2 = sigma_z^2 / (1 + |mu_z|)``."""
    model.eval()
    likelihood.eval()
    mus, vs = [], []
    on_cuda = next(model.parameters()).device.type == "cuda"
    chunk = cfg.predict_chunk_cuda if on_cuda else cfg.predict_chunk
    with torch.no_grad(), gpytorch.settings.fast_pred_var():
        for i in range(0, len(x), chunk):
            xt = to_tensor(x[i : i + chunk])
            f = model(xt)
            if cfg.variance == "observed":
                f = likelihood(f)
            mus.append(f.mean.double().cpu().numpy())
            vs.append(f.variance.double().cpu().numpy())
    mu = (np.concatenate(mus) if mus else np.zeros(0)) * scale
    var = np.clip(np.concatenate(vs) if vs else np.zeros(0), 0.0, None) * scale**2
    return mu, var, var / (1.0 + np.abs(mu))  # Eq. 8
