"""``solver=dip``: an untrained deep image prior, for comparison with learned priors.

The occupancy is the output of a small, randomly initialised convolutional decoder fed a fixed
noise volume (Ulyanov, Vedaldi & Lempitsky, "Deep Image Prior", 2018; the decoder layout follows
Heckel & Hand's "deep decoder", 2019): the network's weights, not the voxels, are optimised to
fit the dips with the data term of :mod:`dipnet.solvers.optimize`. Nothing is learned from other
shapes; the regulariser is the architecture (smooth upsampling and few parameters favour compact,
smooth occupancies) together with early stopping (the iteration count and the loss plateau).

Network (:class:`DeepDecoder`), for ``levels = L`` and ``channels = C`` on an ``N^d`` grid:

    z (C, n_0^d), fixed noise  ->  L x [conv k^d -> ReLU -> channel norm -> upsample x2]
                               ->  [conv f^d -> ReLU -> channel norm]  (``fine_kernel = f``, 0: none)
                               ->  conv 1 (C -> 1)  ->  sigmoid(. / T)  ->  x support mask

with ``n_0 = ceil(N / 2^L)`` and the last upsampling landing exactly on ``N``. The ``k^d`` convolutions
run on the coarse levels only (``N / 2`` per axis at most) and the full-resolution layer is a
``1^d`` channel mix (the deep decoder's), so a 64^3 step costs little more than the data term's
operator. A ``3^3`` convolution at full resolution made the 32^3 solve 3x (8 channels) to 9x (16 channels)
slower for IoU 0.871 / 0.837 against 0.841 (bunny, 41 dips, ~500 steps): too slow for 64^3 here.
``T`` falls geometrically from ``temperature_start`` to ``temperature_end`` like the voxel solver's,
so the occupancy ends nearly binary.

Defaults (bunny, 41 dips, 32^3, noise-free; voxel: IoU 0.929): 2 levels with a ``1^3`` full-resolution
layer reached IoU 0.841 after ~500 Adam steps and 0.899 after 1500 (the decoder fits the dips slowly:
its data term stays ~4x the voxel solver's); 3 levels without the full-resolution layer 0.745;
wider (24 channels) or faster (lr 0.03) no better. Measured against voxel at 64^3:
``docs/guide/solvers.md``, "Deep image prior".

deepinv's ``ConvDecoder`` (the generator its ``DeepImagePrior`` recommends; 2D and 3D in recent
versions) puts a ``3^d`` convolution with batch norm after every upsampling, the full-resolution one
included (256 channels by default), and ``DeepImagePrior`` runs a fixed 2,500 Adam steps of an
unweighted ``||y - A G(z)||^2``. Full-resolution ``3^3`` convolutions do not fit a 64^3 solve in
minutes on 2 cores (above), and the fixed loop would lose this
project's weighted data term, support hull, annealing and plateau stop; so this module keeps its
own small decoder inside the shared loop and adds no dependency.
"""

from __future__ import annotations

import math
import numbers
import time

import torch
import torch.nn.functional as F
from torch import nn

from dipnet.core.keywords import forwards_to
from dipnet.core.measurement import DipMeasurement
from dipnet.core.reconstruction import Reconstruction
from dipnet.operators import DipOperator
from dipnet.solvers.base import checked_temperatures, on_operator_slabs
from dipnet.solvers.optimize import OptimisationSolver, seeded


class DeepDecoder(nn.Module):
    """A small convolutional decoder from a fixed noise volume to one occupancy logit volume.

    Args:
        shape: output grid shape ``(N,) * d`` with ``d`` 2 or 3.
        channels: feature channels ``C`` at every level.
        levels: upsampling stages ``L`` (the input has ``ceil(N / 2^L)`` voxels per axis, at least 2).
        kernel_size: odd side of the convolutions on the coarse levels.
        input_std: standard deviation of the fixed noise input.
    """

    def __init__(self, shape: tuple[int, ...], channels: int = 16, levels: int = 3, kernel_size: int = 3,
                 fine_kernel: int = 0, input_std: float = 1.0) -> None:
        super().__init__()
        ndim = len(shape)
        if ndim not in (2, 3) or len(set(shape)) != 1:
            raise ValueError(f"the decoder makes square 2D or cubic 3D volumes, got shape {shape}")
        sizes = (channels, levels, kernel_size, fine_kernel)
        if (any(isinstance(v, bool) or not isinstance(v, numbers.Integral) for v in sizes) or channels < 1
                or levels < 1 or kernel_size < 1 or kernel_size % 2 == 0 or fine_kernel < 0
                or (fine_kernel and fine_kernel % 2 == 0)):
            raise ValueError(f"need whole numbers channels >= 1, levels >= 1, an odd kernel_size and a fine_kernel "
                             f"that is 0 (no full-resolution layer) or odd (an even kernel shifts the grid by half a "
                             f"voxel), got {channels!r}, {levels!r}, {kernel_size!r}, {fine_kernel!r}")
        n = shape[0]
        self.sizes = [max(2, math.ceil(n / 2 ** (levels - i))) for i in range(levels)] + [n]  # input .. output
        conv = nn.Conv3d if ndim == 3 else nn.Conv2d
        self.blocks = nn.ModuleList(
            nn.Sequential(conv(channels, channels, kernel_size, padding=kernel_size // 2, padding_mode="replicate"),
                          nn.ReLU(), nn.GroupNorm(1, channels))  # channel norm over the whole volume
            for _ in range(levels))
        self.fine = nn.Sequential(conv(channels, channels, fine_kernel, padding=fine_kernel // 2,
                                       padding_mode="replicate"),
                                  nn.ReLU(), nn.GroupNorm(1, channels)) if fine_kernel else nn.Identity()
        self.head = conv(channels, 1, 1)
        self.mode = "trilinear" if ndim == 3 else "bilinear"
        self.register_buffer("noise", input_std * torch.randn(1, channels, *([self.sizes[0]] * ndim)))

    def forward(self) -> torch.Tensor:
        """The logit volume ``shape``."""
        x = self.noise
        for block, size in zip(self.blocks, self.sizes[1:]):
            x = F.interpolate(block(x), size=(size,) * (x.ndim - 2), mode=self.mode, align_corners=False)
        return self.head(self.fine(x))[0, 0]


class DeepImagePriorSolver(OptimisationSolver):
    """Occupancy = a randomly initialised :class:`DeepDecoder`'s output, its weights fitted to the dips.

    Args:
        channels, levels, kernel_size: the decoder (:class:`DeepDecoder`).
        temperature_start, temperature_end: sigmoid temperature at the first and last step (geometric
            in between), as in :class:`~dipnet.solvers.voxel.VoxelSolver`.
        **options: :class:`~dipnet.solvers.optimize.OptimisationSolver` options (iterations, lr,
            optimizer, schedule, tol, window, priors, seed, threshold, progress, ...). The seed draws
            the network's weights and its noise input; ``warm_start`` is not supported.
    """

    name = "dip"
    seeded_start = True  # the seed draws the start (an ensemble member needs no random warm start)

    @forwards_to(OptimisationSolver)
    def __init__(self, channels: int = 16, levels: int = 2, kernel_size: int = 3, fine_kernel: int = 1,
                 temperature_start: float = 1.0,
                 temperature_end: float = 0.25, **options) -> None:
        options.setdefault("iterations", 1000)
        options.setdefault("lr", 0.01)
        options.setdefault("tol", 1e-4)
        options.setdefault("window", 50)
        options.setdefault("priors", {})
        super().__init__(**options)
        if self.warm_start is not None:
            raise ValueError("solver=dip takes no warm_start: its start is the random network of its seed")
        temperature_start, temperature_end = checked_temperatures(temperature_start, temperature_end)
        DeepDecoder((8, 8), channels, levels, kernel_size, fine_kernel)  # validate the network options now
        self.channels, self.levels, self.kernel_size = int(channels), int(levels), int(kernel_size)
        self.fine_kernel = int(fine_kernel)
        self.temperature_start, self.temperature_end = float(temperature_start), float(temperature_end)

    def temperature(self, fraction: float) -> float:
        """Temperature after ``fraction`` (0..1) of the run."""
        return self.temperature_start * (self.temperature_end / self.temperature_start) ** fraction

    def solve(self, measurement: DipMeasurement, operator: DipOperator) -> Reconstruction:
        """Reconstruct on ``operator.grid``; ``info`` holds the network's size (``network_weights``) and the final
        temperature."""
        started = time.perf_counter()
        measurement = on_operator_slabs(measurement, operator)  # resampled (and warned about) once
        problem = self._problem(measurement, operator)  # an "auto" prior weight stays at the rule's start
        data, priors, mask = problem.data, problem.priors, problem.support.to(torch.float32)
        with seeded(self.seed):
            net = DeepDecoder(operator.grid.shape, self.channels, self.levels, self.kernel_size, self.fine_kernel)
            temp = {"T": self.temperature_start}

            def anneal(p: float) -> None:
                temp["T"] = self.temperature(p)

            def occupancy() -> torch.Tensor:
                return torch.sigmoid(net() / temp["T"]) * mask

            history = self._loop(net.parameters(), occupancy, data, priors, self.iterations,
                                 f"dip {operator.grid.n}^{operator.grid.ndim}", before_step=anneal)
            with torch.no_grad():
                occ = occupancy()
        n_weights = sum(p.numel() for p in net.parameters())
        return self._result(occ, operator, history, started, data=data, priors=priors, network_weights=n_weights,
                            final_temperature=temp["T"], support_voxels=int(mask.sum()))
