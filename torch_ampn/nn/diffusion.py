r"""ROBIN mode: a :class:`~torch_ampn.nn.RobinAMPN` as a DDPM denoiser with ``K`` diffusion steps.

Parameterisation (following ROBIN, arXiv 2506.06045, as described in docs/model.md):

* **Target** :math:`x_0`: the normalised residual :math:`\Delta u^t` of the ``l0`` nodes,
  ``[N_0, C]``. The conditioning (node and edge features) is the same at every step; only the
  noise input of the network (:math:`x_k`) and the step encoding change.
* **Schedule**: geometric betas :math:`\beta_k = \beta_{min} (\beta_{max} / \beta_{min})^{(k-1)/(K-1)}`,
  :math:`k = 1 .. K`, from :math:`10^{-4}` to :math:`1`; :math:`\bar\alpha_k = \prod_{s \le k}(1-\beta_s)`.
  Because :math:`\beta_K = 1`, :math:`\bar\alpha_K = 0`: the last step is pure noise (zero
  terminal SNR), so sampling starts exactly from the training distribution of :math:`x_K`.
  For ``K = 1`` the single beta is :math:`\beta_{max} = 1`.
* **Forward process** :math:`x_k = \sqrt{\bar\alpha_k}\, x_0 + \sqrt{1-\bar\alpha_k}\, \epsilon`.
* **v-prediction** with the sign chosen so that :math:`v = x_0` at :math:`\bar\alpha = 0`:
  :math:`v_k = \sqrt{1-\bar\alpha_k}\, x_0 - \sqrt{\bar\alpha_k}\, \epsilon` (the negative of
  Salimans & Ho's :math:`v`). Then
  :math:`\hat x_0 = \sqrt{\bar\alpha_k}\, x_k + \sqrt{1-\bar\alpha_k}\, \hat v`.
  v-prediction stays well posed at :math:`\bar\alpha = 0`, where :math:`\epsilon`-prediction
  cannot recover :math:`x_0`.
* **Training**: per graph a step :math:`k \sim U\{1..K\}`, :math:`\epsilon \sim N(0, I)`,
  loss :math:`\mathrm{MSE}(\hat v, v_k)` (over the ``node_mask`` nodes).
* **Sampling**: ancestral DDPM from :math:`x_K \sim N(0, I)`; at each step :math:`\hat x_0`
  from :math:`\hat v`, then the Gaussian posterior :math:`q(x_{k-1} | x_k, \hat x_0)`;
  the last step returns :math:`\hat x_0`.

**K = 1 is AMPN**: :math:`\bar\alpha_1 = 0`, so :math:`x_1 = \epsilon` is pure N(0, 1) noise,
:math:`v_1 = x_0` and :math:`\hat x_0 = \hat v`: the network gets N(0, 1) noise as its noise
input and directly predicts the residual, the loss is the plain MSE against the target, and
sampling is one forward pass. The step index the network sees is 0-based (``k - 1``).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torch_geometric.nn.aggr import Aggregation

from torch_ampn.hierarchy.hierarchical_data import CONTACT, MESH
from torch_ampn.nn.ampn import AMPN, EdgeType
from torch_ampn.nn.encoding import FourierLevelEncoding

#: Numbers of diffusion steps compared in the seed paper's Table 1.
PAPER_NUM_STEPS = (1, 5, 10, 20)


def masked_mean(values: Tensor, node_mask: Tensor | None = None) -> Tensor:
    """Mean of ``values`` ``[N, C]`` over the rows where ``node_mask`` ``[N]`` is set (all if ``None``)."""
    if node_mask is None:
        return values.mean()
    w = node_mask.to(values.dtype).unsqueeze(-1)  # [N, 1]
    return (values * w).sum() / (w.sum() * values.size(-1)).clamp(min=1.0)


def pointwise_loss(error: Tensor, huber_delta: float | None = None) -> Tensor:
    r"""Squared error, or with ``huber_delta`` its Huber form scaled to match it near zero.

    :math:`e^2` for :math:`|e| \le \delta`, :math:`2 \delta |e| - \delta^2` beyond (continuous
    with a continuous slope; twice :func:`torch.nn.functional.huber_loss`). Outliers then pull
    with a bounded gradient :math:`2 \delta` instead of :math:`2 |e|`.

    Args:
        error: Any shape.
        huber_delta: :math:`\delta > 0`; ``None``: plain squared error.

    Returns:
        Tensor of ``error``'s shape.
    """
    if huber_delta is None:
        return error.square()
    if huber_delta <= 0:
        raise ValueError(f"huber_delta must be positive, got {huber_delta}")
    return 2.0 * F.huber_loss(error, torch.zeros_like(error), reduction="none", delta=huber_delta)


def geometric_beta_schedule(
    num_steps: int, beta_min: float = 1e-4, beta_max: float = 1.0, dtype: torch.dtype = torch.float64
) -> Tensor:
    r"""Geometric noise schedule ``[K]`` (float64).

    :math:`\beta_k = \beta_{min} (\beta_{max}/\beta_{min})^{(k-1)/(K-1)}`, ``k = 1 .. K``;
    ``K = 1`` gives ``[beta_max]``.
    """
    if num_steps < 1:
        raise ValueError(f"num_steps must be >= 1, got {num_steps}")
    if not 0.0 < beta_min <= beta_max <= 1.0:
        raise ValueError(f"need 0 < beta_min <= beta_max <= 1, got {beta_min}, {beta_max}")
    if num_steps == 1:
        return torch.tensor([beta_max], dtype=dtype)
    t = torch.linspace(0.0, 1.0, num_steps, dtype=torch.float64)
    return (beta_min * (beta_max / beta_min) ** t).to(dtype)


class RobinAMPN(AMPN):
    r"""The :class:`AMPN` of ROBIN and the forming surrogate: contact, a noise input, step conditioning.

    An :class:`AMPN` with ``relations=("mesh", "contact")`` whose ``l0`` input is followed by a
    noise input (``noise_channels`` columns: the noisy target in ROBIN mode, N(0, 1) samples in
    the paper's AMPN mode) and, with ``num_step_frequencies > 0``, conditioned on the diffusion
    step (its :class:`FourierLevelEncoding` is the :class:`AMPN`'s ``cond``). The denoiser of
    :class:`DiffusionAMPN`.

    Args:
        fine_in_channels: Node features of ``l0``, without the noise input.
        coarse_in_channels: Node features of coarse levels.
        edge_channels: See :class:`AMPN` (the forming sizes: :func:`torch_ampn.forming.ampn_channels`).
        out_channels: Size of the prediction per ``l0`` node (3: the residual).
        hidden_channels: See :class:`AMPN`.
        num_levels: See :class:`AMPN`.
        pre_layers: See :class:`AMPN`.
        down_layers: See :class:`AMPN`.
        solve_layers: See :class:`AMPN`.
        post_layers: See :class:`AMPN`.
        up_layers: See :class:`AMPN`.
        aggr: See :class:`AMPN`.
        mlp_channels: See :class:`AMPN`.
        noise_channels: Columns of the noise input; 0: none (a deterministic network).
        num_level_frequencies: See :class:`AMPN`.
        num_step_frequencies: Frequencies of the diffusion-step encoding; 0 (default): no step
            conditioning (AMPN, ``K = 1``).
        max_step: Largest diffusion-step index the step encoding separates.
    """

    def __init__(
        self,
        fine_in_channels: int,
        coarse_in_channels: int,
        edge_channels: int | Mapping[str, int],
        out_channels: int = 3,
        hidden_channels: int = 128,
        num_levels: int = 4,
        pre_layers: int = 3,
        down_layers: int = 2,
        solve_layers: int = 5,
        post_layers: int = 3,
        up_layers: int = 2,
        aggr: str | Aggregation = "max",
        mlp_channels: int = 128,
        noise_channels: int = 0,
        num_level_frequencies: int = 4,
        num_step_frequencies: int = 0,
        max_step: int = 20,
    ) -> None:
        step_encoding = (
            FourierLevelEncoding(num_step_frequencies, max_index=float(max_step))
            if num_step_frequencies > 0
            else None
        )
        super().__init__(
            fine_in_channels + noise_channels,
            out_channels,
            edge_channels,
            hidden_channels=hidden_channels,
            num_levels=num_levels,
            pre_layers=pre_layers,
            down_layers=down_layers,
            solve_layers=solve_layers,
            post_layers=post_layers,
            up_layers=up_layers,
            aggr=aggr,
            mlp_channels=mlp_channels,
            coarse_in_channels=coarse_in_channels,
            relations=(MESH, CONTACT),
            num_level_frequencies=num_level_frequencies,
            cond_channels=0 if step_encoding is None else step_encoding.out_channels,
            # the seed paper's V-cycle, whatever the generic AMPN's defaults: the forming
            # surrogates normalise their own inputs and were tuned with these
            transfer_weights=False,
            coarse_inputs="none",
            normalize=False,
            mlp_norm=True,
        )
        self.fine_in_channels = fine_in_channels
        self.noise_channels = noise_channels
        self.step_encoding = step_encoding

    def forward(  # type: ignore[override]
        self,
        x_dict: dict[str, Tensor],
        edge_index_dict: dict[EdgeType, Tensor],
        edge_attr_dict: dict[EdgeType, Tensor],
        noise: Tensor | None = None,
        step: Tensor | None = None,
        batch_dict: dict[str, Tensor] | None = None,
        contact_mask_dict: dict[EdgeType, Tensor] | None = None,
    ) -> Tensor:
        """Predict the ``l0`` output, ``[N_0, out_channels]``.

        Args:
            x_dict: See :meth:`AMPN.forward` (``l0``: ``fine_in_channels`` columns).
            edge_index_dict: See :meth:`AMPN.forward`.
            edge_attr_dict: See :meth:`AMPN.forward`.
            noise: Noise input of ``l0`` ``[N_0, noise_channels]`` (models with
                ``noise_channels > 0`` only).
            step: Diffusion-step index (models with step conditioning only): a number or
                scalar tensor (every graph) or ``LongTensor[B]`` (one per graph, with ``batch_dict``).
            batch_dict: See :meth:`AMPN.forward`.
            contact_mask_dict: See :meth:`AMPN.forward`.
        """
        if self.noise_channels > 0:
            if noise is None:
                raise ValueError(
                    f"this AMPN has a noise input ({self.noise_channels} channels): pass `noise` "
                    "(or build it with noise_channels=0)"
                )
            x = x_dict["l0"]
            x_dict = {**x_dict, "l0": torch.cat([x, noise.to(x.dtype)], dim=-1)}
        step_code = None
        if self.step_encoding is not None:
            if step is None:
                raise ValueError("this AMPN is conditioned on the diffusion step: pass `step`")
            step_code = self.step_encoding(step)  # [2F'] or [B, 2F']
        return super().forward(
            x_dict, edge_index_dict, edge_attr_dict, batch_dict, contact_mask_dict, cond=step_code
        )

    def extra_repr(self) -> str:
        """Constructor arguments shown by ``repr``."""
        return (
            f"fine_in_channels={self.fine_in_channels}, coarse_in_channels={self.coarse_in_channels}, "
            f"out_channels={self.out_channels}, hidden_channels={self.hidden_channels}, "
            f"mlp_channels={self.mlp_channels}, noise_channels={self.noise_channels}, "
            f"num_levels={self.num_levels}, aggr={self.aggr!r}"
        )


class DiffusionAMPN(nn.Module):
    r"""A :class:`~torch_ampn.nn.RobinAMPN` used as a v-predicting DDPM denoiser (ROBIN mode).

    See the module docstring for the parameterisation; ``num_steps=1`` is plain AMPN
    training and inference.

    Args:
        model: The denoiser. Its ``noise_channels`` must equal ``out_channels`` (the noisy
            target enters as the noise input); for ``num_steps > 1`` it must be built with
            ``num_step_frequencies > 0`` and ``max_step >= num_steps - 1``.
        num_steps: Number of diffusion steps ``K`` (the paper compares 1, 5, 10, 20).
        beta_min: First beta of the geometric schedule.
        beta_max: Last beta (1: zero terminal SNR).
    """

    betas: Tensor
    alphas_bar: Tensor

    def __init__(
        self, model: RobinAMPN, num_steps: int = 1, beta_min: float = 1e-4, beta_max: float = 1.0
    ) -> None:
        super().__init__()
        if model.noise_channels != model.out_channels:
            raise ValueError(
                f"the denoiser's noise input ({model.noise_channels} channels) must match its output "
                f"({model.out_channels} channels)"
            )
        if num_steps > 1 and model.step_encoding is None:
            raise ValueError("num_steps > 1 needs a model with step conditioning (num_step_frequencies > 0)")
        self.model = model
        self.num_steps = num_steps
        self.beta_min = beta_min
        self.beta_max = beta_max
        betas = geometric_beta_schedule(num_steps, beta_min, beta_max)  # [K] float64
        self.register_buffer("betas", betas, persistent=False)
        self.register_buffer("alphas_bar", torch.cumprod(1.0 - betas, 0), persistent=False)
        # the same schedule as Python floats (sampling; traceable by torch.compile)
        self._schedule = (betas.tolist(), torch.cumprod(1.0 - betas, 0).tolist())

    def _step_arg(self, step: Tensor) -> Tensor | None:
        return step if self.model.step_encoding is not None else None

    def q_sample(self, x0: Tensor, noise: Tensor, alpha_bar: Tensor) -> tuple[Tensor, Tensor]:
        """Noisy sample and v target ``(x_k, v_k)``, both ``[N, C]``; ``alpha_bar`` is ``[N, 1]``."""
        a, s = alpha_bar.sqrt(), (1.0 - alpha_bar).sqrt()
        return a * x0 + s * noise, s * x0 - a * noise

    def error(
        self,
        target: Tensor,
        x_dict: dict[str, Tensor],
        edge_index_dict: dict[EdgeType, Tensor],
        edge_attr_dict: dict[EdgeType, Tensor],
        batch_dict: dict[str, Tensor] | None = None,
        contact_mask_dict: dict[EdgeType, Tensor] | None = None,
        noise: Tensor | None = None,
        step: Tensor | None = None,
        generator: torch.Generator | None = None,
        network: nn.Module | None = None,
    ) -> Tensor:
        r"""Error :math:`\hat v - v` of every ``l0`` node at a random step per graph, ``[N_0, C]`` (float32).

        :meth:`loss` reduces it; a multilevel loss (:func:`~torch_ampn.nn.multilevel_mse`) restricts it.

        Args:
            target: Normalised residual :math:`x_0` of the ``l0`` nodes, ``[N_0, C]``.
            x_dict: See :meth:`AMPN.forward`.
            edge_index_dict: See :meth:`AMPN.forward`.
            edge_attr_dict: See :meth:`AMPN.forward`.
            batch_dict: Graph of every node per level (batched data): one step per graph.
            contact_mask_dict: See :meth:`AMPN.forward`.
            noise: :math:`\epsilon` ``[N_0, C]``; drawn (first) from ``generator`` if ``None``.
            step: 0-based steps ``LongTensor[B]``; drawn (second) from ``generator`` if ``None``.
            generator: Random generator for ``noise`` and ``step``.
            network: Callable run in place of :attr:`model` with the same parameters, e.g.
                ``torch.compile(self.model)`` (kept out of the module tree, so checkpoints keep
                their keys); ``None``: :attr:`model`.

        Returns:
            ``[N_0, C]``.
        """
        batch = None if batch_dict is None else batch_dict.get("l0")
        num_graphs = 1 if batch is None else int(batch.max()) + 1 if batch.numel() > 0 else 1
        if noise is None:
            noise = torch.randn(target.shape, generator=generator, dtype=target.dtype, device=target.device)
        if step is None:
            step = torch.randint(
                0, self.num_steps, (num_graphs,), generator=generator, device=target.device
            )  # [B]
        step = step.to(target.device).long().reshape(-1)
        alpha_bar = self.alphas_bar.to(target.device)[step]  # [B]
        alpha_bar = alpha_bar[batch] if batch is not None else alpha_bar.expand(target.size(0))
        alpha_bar = alpha_bar.unsqueeze(-1).to(target.dtype)  # [N, 1]
        x_k, v = self.q_sample(target, noise, alpha_bar)
        v_hat = (self.model if network is None else network)(
            x_dict,
            edge_index_dict,
            edge_attr_dict,
            noise=x_k,
            step=self._step_arg(step),
            batch_dict=batch_dict,
            contact_mask_dict=contact_mask_dict,
        )
        return v_hat.float() - v.float()

    def loss(
        self,
        *args: Any,
        node_mask: Tensor | None = None,
        huber_delta: float | None = None,
        **kwargs: Any,
    ) -> Tensor:
        r"""The training loss: MSE between predicted and true ``v`` at a random step per graph.

        With ``K = 1`` this is the plain MSE of AMPN against the normalised residual.

        Args:
            *args: ``target, x_dict, edge_index_dict, edge_attr_dict`` of :meth:`error`.
            node_mask: ``BoolTensor[N_0]``: nodes that enter the loss (e.g. ply nodes); all if ``None``.
            huber_delta: Use the Huber form of the squared error beyond this error
                (:func:`pointwise_loss`); ``None``: plain MSE (the paper).
            **kwargs: The other arguments of :meth:`error` (``batch_dict``, ``contact_mask_dict``,
                ``noise``, ``step``, ``generator``, ``network``).

        Returns:
            Scalar loss (float32).
        """
        return masked_mean(pointwise_loss(self.error(*args, **kwargs), huber_delta), node_mask)

    def sample(
        self,
        x_dict: dict[str, Tensor],
        edge_index_dict: dict[EdgeType, Tensor],
        edge_attr_dict: dict[EdgeType, Tensor],
        contact_mask_dict: dict[EdgeType, Tensor] | None = None,
        generator: torch.Generator | None = None,
        noise: Tensor | None = None,
        network: nn.Module | None = None,
        draw: Callable[[], Tensor] | None = None,
    ) -> Tensor:
        r"""``K``-step ancestral sampling of the normalised residual, ``[N_0, C]``.

        Runs the model ``K`` times (no gradient is disabled here: wrap the call in
        ``torch.no_grad()`` for inference). Every graph of a batch is at the same step.

        Args:
            x_dict: See :meth:`AMPN.forward`.
            edge_index_dict: See :meth:`AMPN.forward`.
            edge_attr_dict: See :meth:`AMPN.forward`.
            contact_mask_dict: See :meth:`AMPN.forward`.
            generator: Random generator for the initial noise and the posterior noise.
            noise: Initial :math:`x_K` ``[N_0, C]`` (drawn from ``generator`` if ``None``).
            network: Runs in place of the AMPN (e.g. its ``torch.compile`` wrapper).
            draw: Returns the next ``[N_0, C]`` standard normal sample, in place of
                ``torch.randn(..., generator=generator)`` (the initial noise, then one per step).

        Returns:
            :math:`\hat x_0`, ``[N_0, C]``.
        """
        x0_feat = x_dict["l0"]
        shape = (x0_feat.size(0), self.model.out_channels)
        dtype, device = x0_feat.dtype, x0_feat.device
        if draw is None:

            def draw() -> Tensor:
                return torch.randn(shape, generator=generator, dtype=dtype, device=device)

        model = self.model if network is None else network
        x = draw() if noise is None else noise
        betas, alphas_bar = self._schedule
        for k in range(self.num_steps - 1, -1, -1):
            step = torch.tensor(k, device=device)
            v_hat = model(
                x_dict,
                edge_index_dict,
                edge_attr_dict,
                noise=x,
                step=self._step_arg(step),
                contact_mask_dict=contact_mask_dict,
            ).to(dtype)
            ab = alphas_bar[k]
            x0_hat = ab**0.5 * x + (1.0 - ab) ** 0.5 * v_hat
            if k == 0:
                return x0_hat
            ab_prev, beta = alphas_bar[k - 1], betas[k]
            coef_x0 = ab_prev**0.5 * beta / (1.0 - ab)
            coef_xk = (1.0 - beta) ** 0.5 * (1.0 - ab_prev) / (1.0 - ab)
            var = beta * (1.0 - ab_prev) / (1.0 - ab)
            z = draw()
            x = coef_x0 * x0_hat + coef_xk * x + var**0.5 * z
        raise AssertionError("unreachable")  # pragma: no cover

    def extra_repr(self) -> str:
        """Schedule parameters shown by ``repr``."""
        return f"num_steps={self.num_steps}, beta_min={self.beta_min}, beta_max={self.beta_max}"
