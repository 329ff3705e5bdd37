"""Setting-aware baselines: predictors of a whole trajectory from its process settings.

A surrogate exists to predict the part for process settings nobody simulated; the strongest
simple predictors built from the same training trajectories set the bar it must clear:

* :class:`MeanTrajectory`: the mean of the training trajectories, whatever the settings;
* :class:`NearestSetting`: the training trajectory whose settings are nearest (in settings
  standardised by their spread over the training set);
* :class:`PODRegression`: the classical reduced-order surrogate of design studies: a principal
  component (POD) basis of the training trajectories, and a regression of each trajectory's
  coefficients on its settings (a Gaussian process, radial basis functions or a linear map:
  scikit-learn and scipy).

All work on datasets of one mesh (every trajectory has the same nodes, components and number
of steps): they predict the ply nodes' positions at every saved step, ``[T+1, N, 3]``, and copy
the tools' prescribed motion from the trajectory asked about. The settings of a trajectory are
:func:`process_settings`: each gripper's position along its free edge (a fraction) and its
force (N).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from torch_ampn.data.trajectory import Trajectory


def process_settings(traj: Trajectory) -> Tensor:
    """The process settings of ``traj``: ``[2G]`` float64, gripper edge fractions then forces (N).

    The edge fractions come from ``meta["gripper_edge_fraction"]`` (written by the embedded
    simulator and by :func:`~torch_ampn.sim.process_trajectory`).

    Raises:
        ValueError: If the trajectory does not record its gripper positions.
    """
    where = traj.meta.get("gripper_edge_fraction")
    if where is None:
        name = traj.meta.get("name", "trajectory")
        raise ValueError(f"{name}: meta has no 'gripper_edge_fraction' (its gripper positions)")
    where = torch.as_tensor(where, dtype=torch.float64).reshape(-1)
    force = traj.gripper_force.double().reshape(-1)
    if where.numel() != force.numel():
        raise ValueError(
            f"{traj.meta.get('name', 'trajectory')}: {where.numel()} gripper positions "
            f"but {force.numel()} forces"
        )
    return torch.cat([where, force])


def setting_names(num_grippers: int) -> list[str]:
    """Names of the entries of :func:`process_settings`."""
    return [f"gripper{g}_position" for g in range(num_grippers)] + [
        f"gripper{g}_force_N" for g in range(num_grippers)
    ]


class TrajectoryBaseline:
    """A predictor of a trajectory's ply positions from its settings, fitted on training trajectories.

    Subclasses implement :meth:`_fit` and :meth:`_predict` on flattened ply positions.
    """

    #: Whether the inputs are the process settings and the part's parameters
    #: (:func:`~torch_ampn.baselines.family.part_parameters`) and only the plies must share a mesh:
    #: parts of a family with one ply count (:class:`~torch_ampn.baselines.family.PerPlyCount`).
    parts: bool = False

    def __init__(self) -> None:
        self._template: Trajectory | None = None

    def settings_of(self, traj: Trajectory) -> Tensor:
        """The inputs of ``traj``, ``[S]`` float64.

        :func:`process_settings`, and with :attr:`parts` the part's parameters after them.
        """
        if not self.parts:
            return process_settings(traj)
        from torch_ampn.baselines.family import part_parameters

        return torch.cat([process_settings(traj), part_parameters(traj)])

    # ---- fitting ------------------------------------------------------------------------
    def fit(self, trajectories: Sequence[Trajectory]) -> TrajectoryBaseline:
        """Fit on ``trajectories`` (one mesh); returns ``self``.

        Raises:
            ValueError: If there are none, or they are not of one mesh (the message names the first
                that differs and how).
        """
        trajectories = list(trajectories)
        if not trajectories:
            raise ValueError(f"{type(self).__name__}.fit needs at least one trajectory")
        first = trajectories[0]
        for traj in trajectories[1:]:
            _check_same_mesh(first, traj, plies_only=self.parts)
        self._template = first
        settings = torch.stack([self.settings_of(t) for t in trajectories]).numpy()  # [M, S]
        positions = torch.stack([t.pos[:, t.ply_mask].double() for t in trajectories])  # [M, T+1, P, 3]
        self._shape = tuple(positions.shape[1:])
        self._fit(settings, positions.reshape(len(trajectories), -1).numpy())
        return self

    def _fit(self, settings: np.ndarray, positions: np.ndarray) -> None:
        """``settings [M, S]``, ``positions [M, D]`` (D = (T+1) P 3, float64)."""
        raise NotImplementedError

    def _predict(self, settings: np.ndarray) -> np.ndarray:
        """``settings [B, S]`` -> ``positions [B, D]``."""
        raise NotImplementedError

    # ---- predicting ---------------------------------------------------------------------
    def predict_settings(self, settings: Tensor | Sequence[Sequence[float]]) -> Tensor:
        """Ply positions for each row of ``settings`` ``[B, S]``: ``[B, T+1, P, 3]`` float32."""
        if self._template is None:
            raise RuntimeError(f"{type(self).__name__}: call fit() first")
        x = torch.as_tensor(settings, dtype=torch.float64)
        x = x.reshape(1, -1) if x.dim() == 1 else x
        expected = self.settings_of(self._template).numel()
        if x.size(1) != expected:
            grippers = process_settings(self._template).numel() // 2
            what = ", ".join(setting_names(grippers)) + (" and the part's parameters" if self.parts else "")
            raise ValueError(f"settings need {expected} columns ({what}), got {x.size(1)}")
        out = self._predict(x.numpy())  # [B, D]
        return torch.from_numpy(np.array(out, dtype=np.float64)).float().reshape(x.size(0), *self._shape)

    def predict(self, traj: Trajectory) -> Tensor:
        """The predicted trajectory for ``traj``'s settings, ``[T+1, N, 3]``.

        Ply nodes are predicted; the tools' nodes take ``traj``'s (prescribed) positions.

        Raises:
            ValueError: If ``traj`` is not on the training mesh.
        """
        return self.predict_many([traj])[0]

    def predict_many(self, trajectories: Sequence[Trajectory]) -> list[Tensor]:
        """:meth:`predict` of several trajectories of the training mesh in one batch of settings."""
        if self._template is None:
            raise RuntimeError(f"{type(self).__name__}: call fit() first")
        trajs = list(trajectories)
        if not trajs:
            return []
        for traj in trajs:
            _check_same_mesh(self._template, traj, plies_only=self.parts)
        plies = self.predict_settings(torch.stack([self.settings_of(t) for t in trajs]))  # [B, T+1, P, 3]
        out = []
        for traj, ply_pos in zip(trajs, plies, strict=True):
            pos = traj.pos.clone().float()
            pos[:, traj.ply_mask] = ply_pos
            out.append(pos)
        return out

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"


def _check_same_mesh(reference: Trajectory, traj: Trajectory, plies_only: bool = False) -> None:
    """Raise a one-line ``ValueError`` where ``traj`` is not on ``reference``'s mesh.

    With ``plies_only``: where its plies are not on ``reference``'s plies (the tools may differ).
    """
    name = traj.meta.get("name", "a trajectory")
    ref_name = reference.meta.get("name", "the first")
    ref_ply, ply = (reference.ply_mask, traj.ply_mask) if plies_only else (slice(None), slice(None))
    ref_pos, pos = reference.pos[:, ref_ply], traj.pos[:, ply]
    checks = [
        ("pos", tuple(pos.shape) == tuple(ref_pos.shape), f"shape {list(pos.shape)}"),
        ("component", torch.equal(traj.component[ply], reference.component[ref_ply]), "other components"),
        ("node_type", torch.equal(traj.node_type[ply], reference.node_type[ref_ply]), "other node types"),
        (
            "gripper_force",
            traj.gripper_force.numel() == reference.gripper_force.numel(),
            "another gripper count",
        ),
    ]
    for field, ok, what in checks:
        if not ok:
            raise ValueError(
                f"{name}: field {field!r} differs from {ref_name}'s ({what}): the setting-aware "
                "baselines need trajectories of one mesh"
            )
    if not torch.allclose(pos[0], ref_pos[0], atol=1e-4, rtol=0):
        raise ValueError(
            f"{name}: field 'pos' starts elsewhere than {ref_name}'s (another mesh): the setting-aware "
            "baselines need trajectories of one mesh"
        )


class MeanTrajectory(TrajectoryBaseline):
    """The mean of the training trajectories (ply positions at every step), whatever the settings."""

    def _fit(self, settings: np.ndarray, positions: np.ndarray) -> None:
        self._mean = positions.mean(0)  # [D]

    def _predict(self, settings: np.ndarray) -> np.ndarray:
        return np.broadcast_to(self._mean, (settings.shape[0], self._mean.size))


def _standardiser(settings: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centre and scale ``[S]`` of the training settings (a constant setting gets scale 1)."""
    centre, scale = settings.mean(0), settings.std(0)
    return centre, np.where(scale > 0, scale, 1.0)


class NearestSetting(TrajectoryBaseline):
    """The training trajectory with the nearest settings.

    Distance: Euclidean on settings standardised by their mean and standard deviation over the
    training trajectories (gripper positions are fractions, forces newtons); the first of equals.
    """

    def _fit(self, settings: np.ndarray, positions: np.ndarray) -> None:
        self._centre, self._scale = _standardiser(settings)
        self._x = (settings - self._centre) / self._scale  # [M, S]
        self._y = positions

    def nearest(self, settings: np.ndarray) -> np.ndarray:
        """Index of the nearest training trajectory for each row of ``settings`` ``[B, S]``: ``[B]``."""
        z = (np.asarray(settings, dtype=np.float64) - self._centre) / self._scale
        return ((z[:, None, :] - self._x[None]) ** 2).sum(-1).argmin(1)

    def _predict(self, settings: np.ndarray) -> np.ndarray:
        return self._y[self.nearest(settings)]


Regressor = Literal["gp", "rbf", "linear"]


class PODRegression(TrajectoryBaseline):
    r"""POD of the training trajectories and a regression of the coefficients on the settings.

    With the training ply positions as rows :math:`y_m \in \mathbb{R}^D` (all steps), their mean
    :math:`\bar y` and the leading principal directions :math:`\Phi \in \mathbb{R}^{D \times r}`
    (scikit-learn's ``PCA``), a trajectory is :math:`\bar y + \Phi\, c(s)`, where the coefficients
    :math:`c` are regressed on the standardised settings :math:`s`:

    * ``"gp"``: a Gaussian process (scikit-learn's ``GaussianProcessRegressor``, a constant
      times an anisotropic RBF kernel, one length scale per setting, plus a white-noise term
      when ``noise``; hyperparameters by maximum likelihood; the coefficients scaled by one
      common factor, so that the leading components dominate the likelihood);
    * ``"rbf"``: radial basis function interpolation (scipy's ``RBFInterpolator``,
      thin-plate spline with a linear polynomial, ``smoothing``);
    * ``"linear"``: least squares, an affine map of the settings (scikit-learn's
      ``LinearRegression``), which is a linear regression of every coordinate on the settings.

    With all components kept (``num_components=None``), no noise term and no smoothing, the
    GP and RBF surrogates reproduce the training trajectories exactly.

    Args:
        regressor: ``"gp"``, ``"rbf"`` or ``"linear"``.
        num_components: Components kept: an int, a fraction of the variance to explain
            (``0 < f < 1``), or ``None`` for all (at most ``M - 1`` for ``M`` trajectories).
        noise: GP only: fit a white-noise term (the simulator's own scatter); ``False``
            interpolates.
        smoothing: RBF only: scipy's smoothing parameter (0 interpolates).
        restarts: GP only: optimiser restarts from random hyperparameters.
        seed: GP only: seed of those restarts.
    """

    def __init__(
        self,
        regressor: Regressor = "gp",
        num_components: int | float | None = 0.999,
        noise: bool = True,
        smoothing: float = 0.0,
        restarts: int = 3,
        seed: int = 0,
    ) -> None:
        super().__init__()
        if regressor not in ("gp", "rbf", "linear"):
            raise ValueError(f"regressor must be 'gp', 'rbf' or 'linear', got {regressor!r}")
        if isinstance(num_components, float) and not 0 < num_components < 1:
            raise ValueError(f"a fractional num_components must be in (0, 1), got {num_components}")
        if isinstance(num_components, int) and num_components < 1:
            raise ValueError(f"num_components must be >= 1, got {num_components}")
        self.regressor, self.num_components = regressor, num_components
        self.noise, self.smoothing, self.restarts, self.seed = (
            noise,
            float(smoothing),
            int(restarts),
            int(seed),
        )

    def _fit(self, settings: np.ndarray, positions: np.ndarray) -> None:
        from sklearn.decomposition import PCA

        m = positions.shape[0]
        self._centre, self._scale = _standardiser(settings)
        x = (settings - self._centre) / self._scale  # [M, S]
        self._mean = positions.mean(0)  # [D]
        centred = positions - self._mean
        rank = max(1, m - 1)
        if isinstance(self.num_components, float):
            pca = PCA(n_components=rank, svd_solver="full").fit(centred)
            explained = np.cumsum(pca.explained_variance_ratio_)
            keep = int(np.searchsorted(explained, self.num_components) + 1) if explained[-1] > 0 else 1
        else:
            pca = PCA(n_components=min(self.num_components or rank, rank), svd_solver="full").fit(centred)
            keep = pca.n_components_
        self._basis = pca.components_[:keep]  # [r, D]
        self.explained_variance_ratio = pca.explained_variance_ratio_[:keep]
        coeffs = centred @ self._basis.T  # [M, r]
        self._model = self._regression(x, coeffs)

    def _regression(self, x: np.ndarray, coeffs: np.ndarray):
        if self.regressor == "linear":
            from sklearn.linear_model import LinearRegression

            return LinearRegression().fit(x, coeffs)
        if self.regressor == "rbf":
            from scipy.interpolate import RBFInterpolator

            degree = 1 if x.shape[0] > x.shape[1] else 0  # a linear tail needs S + 1 points
            return RBFInterpolator(
                x, coeffs, kernel="thin_plate_spline", smoothing=self.smoothing, degree=degree
            )
        from sklearn.gaussian_process import GaussianProcessRegressor
        from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel

        kernel = ConstantKernel(1.0, (1e-3, 1e3)) * RBF(np.ones(x.shape[1]), (1e-2, 1e2))
        if self.noise:
            kernel = kernel + WhiteKernel(1e-2, (1e-8, 1e1))
        # one scale for all coefficients (not normalize_y's per target): the leading components
        # weigh in the likelihood as much as they weigh in the trajectories
        scale = float(np.sqrt(np.mean(coeffs**2))) or 1.0
        gp = GaussianProcessRegressor(
            kernel, alpha=1e-10, n_restarts_optimizer=self.restarts, random_state=self.seed
        )
        return _GPAdapter(gp.fit(x, coeffs / scale), scale)

    def _predict(self, settings: np.ndarray) -> np.ndarray:
        z = (settings - self._centre) / self._scale
        coeffs = np.asarray(self._model(z) if callable(self._model) else self._model.predict(z))
        return self._mean + coeffs.reshape(z.shape[0], -1) @ self._basis

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(regressor={self.regressor!r}, num_components={self.num_components}, "
            f"noise={self.noise}, smoothing={self.smoothing})"
        )


class _GPAdapter:
    """A fitted ``GaussianProcessRegressor`` with ``predict`` of ``[B, r]`` whatever ``r``."""

    def __init__(self, gp, scale: float) -> None:
        self.gp, self.scale = gp, scale

    def predict(self, z: np.ndarray) -> np.ndarray:
        return self.scale * np.asarray(self.gp.predict(z)).reshape(z.shape[0], -1)


#: The names of :func:`setting_baselines`, in their order.
SETTING_BASELINE_NAMES = ("mean_trajectory", "nearest_setting", "linear_settings", "pod_gp")


def setting_baselines() -> dict[str, TrajectoryBaseline]:
    """The setting-aware baselines reported beside a model, by name (unfitted).

    The mean training trajectory, the nearest training setting, a linear regression on the
    settings, POD + GP.
    """
    made = (
        MeanTrajectory(),
        NearestSetting(),
        PODRegression("linear", num_components=None),
        PODRegression("gp"),
    )
    return dict(zip(SETTING_BASELINE_NAMES, made, strict=True))


def rollout_mse(pred: Tensor, true: Tensor, mask: Tensor | None = None) -> float:
    """Mean squared error of a rollout in mm^2.

    The mean over steps ``1 .. T`` of the squared per-step RMSE (:func:`~torch_ampn.rollout.rollout_rmse`).
    """
    from torch_ampn.rollout import rollout_rmse

    return float(rollout_rmse(pred, true, mask)[1:].double().square().mean())


def setting_effect_r2(mse: float, mse_mean_trajectory: float) -> float:
    r"""Explained variance of the setting effect: :math:`R^2 = 1 - \mathrm{MSE} / \mathrm{MSE}_\text{mean}`.

    ``MSE_mean`` is the error of the mean training trajectory (which ignores the settings), both
    averaged over the same test trajectories (:func:`rollout_mse`): 1 predicts every setting's
    effect, 0 no better than ignoring the settings, below 0 worse.
    """
    if mse_mean_trajectory <= 0:
        raise ValueError(f"the mean trajectory's MSE must be > 0, got {mse_mean_trajectory}")
    return 1.0 - mse / mse_mean_trajectory


def fit_setting_baselines(
    trajectories: Sequence[Trajectory],
    fitted: Mapping[str, TrajectoryBaseline] | None = None,
) -> tuple[dict[str, TrajectoryBaseline], str | None]:
    """:func:`setting_baselines` fitted on ``trajectories``.

    Args:
        trajectories: The training trajectories.
        fitted: Baselines already fitted on the same ``trajectories``, by name (e.g. a
            surrogate's prior): used as they are instead of fitting them again.

    Returns:
        ``(baselines, None)``, or ``({}, reason)`` where they do not apply (fewer than 2
        trajectories, several meshes, no recorded settings). The trajectories of a family of
        parts (each records its ``meta["part"]``) get :func:`~torch_ampn.baselines.family_baselines`.
    """
    trajectories = list(trajectories)
    if len(trajectories) < 2:
        return {}, f"{len(trajectories)} training trajectories (they need at least 2)"
    try:
        for traj in trajectories:
            process_settings(traj)
        if all("part" in traj.meta for traj in trajectories):  # a family of parts: per ply count
            from torch_ampn.baselines.family import family_baselines

            return {name: b.fit(trajectories) for name, b in family_baselines().items()}, None
        fitted = dict(fitted or {})
        return {
            name: fitted[name] if name in fitted else b.fit(trajectories)
            for name, b in setting_baselines().items()
        }, None
    except ValueError as err:
        return {}, str(err)
