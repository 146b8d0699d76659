"""``fourier``: the dip transform by the Fourier-slice theorem and a non-uniform FFT.

Model
-----
Voxel ``v`` is a box of side ``h`` and uniform density ``f_v`` (the *box-voxel model*). The
plane-integral profile ``P_k(t)`` of the volume along ``theta_k`` has the 1D Fourier transform

    P_k^(w) = F^(w theta_k) = D_k(w) * h^d prod_i sinc(h theta_ki w),
    D_k(w)  = sum_v f_v exp(-2 pi i w theta_k . x_v),

(Fourier-slice theorem; ``sinc(x) = sin(pi x) / (pi x)``, the product is the transform of the
voxel box). Slab ``j`` (centre ``c_j``, thickness ``delta``) holds ``g_k(c_j)`` with
``g_k = P_k * box_delta``, so ``g_k^ = P_k^ * delta sinc(delta w)``. ``g_k`` vanishes for
``|t| > S`` (working ball plus half a voxel diagonal plus half a slab), so its samples follow
exactly from the Fourier series of period ``T > S + extent/2`` (no wrap-around onto the
slabs):

    g_k(c_j) = (1/T) sum_n g_k^(n/T) exp(2 pi i n c_j / T).

The series is truncated at ``|n/T| <= bandwidth / (2 delta)`` (``bandwidth`` times the slab
Nyquist frequency); that truncation of the kernel tail is the only approximation besides the
NUFFT tolerance. It is harmless where ``D_k`` decays, but within ~1/N rad of a grid axis the
voxel heights form a near-lattice, ``D_k`` is nearly periodic in ``w`` and the slowly decaying
kernel tail matters: those few orientations use ``axis_boost`` times more frequencies.
Measured against :func:`~dipnet.operators.box_model.box_voxel_profiles` with the defaults:
3e-5 to 8e-5 relative L2 on the shared meshes at 64^3, <= ~1e-3 for the worst single
orientation (a cube seen along a grid axis). The ``n = 0`` term is the exact volume, so
profiles sum to the volume up to the ringing of the truncated kernel outside the slab range
(~1e-7 relative). Against the reference backends (a linear hat kernel per voxel height, not a
box) the difference is the model's: 0.2-0.6 % relative L2 on the shared meshes at 64^3.

Computation: all ``D_k(n/T)`` for ``n >= 0`` (``D_k(-w) = conj D_k(w)`` for a real volume) come
from one type-2 NUFFT of the volume (``finufft``) at ``K x n_freq`` points; they are weighted
by the kernel spectra, folded modulo the period (slab centres are a uniform sub-grid of the
period) and turned into slabs by a length-``M_T`` inverse FFT per orientation. The adjoint runs
the exact transpose of every real-linear step, with the NUFFT's own adjoint (type 1, opposite
sign, same spreading kernel), so ``<A x, y> = <x, A^T y>`` holds to rounding, whatever the
NUFFT tolerance.

Cost ``O((2N)^d log N + K * n_freq * w^d)`` (``n_freq ~ bandwidth * M / 2`` per orientation,
``w`` = spreading width of the NUFFT kernel), with no ``K * N^d`` term.
"""

from __future__ import annotations

import math

import finufft
import numpy as np
import torch

from dipnet.core.counts import is_real, whole_number
from dipnet.core.grid import Grid
from dipnet.operators.base import DipOperator

_SERIAL_LIMIT = 1 << 15  # voxels + frequency samples below which one thread is faster
_AXIS_ANGLE = 2.0  # orientations within _AXIS_ANGLE / N rad of a grid axis get axis_boost


class _FourierApply(torch.autograd.Function):
    """``A`` (``transpose=False``) or ``A^T`` (``transpose=True``), with the other as backward."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, op: "FourierOperator", transpose: bool) -> torch.Tensor:  # type: ignore[override]
        ctx.op, ctx.transpose = op, transpose
        return op._transform(x, transpose)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):  # type: ignore[override]
        return _FourierApply.apply(grad, ctx.op, not ctx.transpose), None, None


#: The largest NUFFT tolerance accepted: a random 24^3 volume's profiles err by 2.7e-5 at eps 1e-3, 2.2e-3 at
#: 1e-2, 7.4e-3 at 3e-2 and 0.16 at 0.1 (relative, against eps 1e-9); a coarse eps ruins the operator silently.
MAX_EPS = 1e-2
#: The NUFFT oversampling factors finufft supports: it refuses 1 or less after the work before it, warns that
#: values outside this range "may break the library", and a NaN crashed the process (segmentation fault).
UPSAMPFAC_RANGE = (1.15, 3.0)


def check_options(bandwidth: float = 4.0, axis_boost: float = 32.0, eps: float = 1e-6, nthreads: int | None = None,
                  upsampfac: float | None = None, single: bool = False) -> None:
    """Raise ``ValueError`` naming the option for a bad option of :class:`FourierOperator` (its defaults pass), so a
    job can check them before any work (:func:`dipnet.jobs.options.check_operator`)."""
    for name, value in (("bandwidth", bandwidth), ("axis_boost", axis_boost)):
        if not is_real(value) or not 1.0 <= value < math.inf:
            raise ValueError(f"{name} must be a finite number >= 1 (a multiple of the slab Nyquist frequency), "
                             f"got {value!r}")
    if not is_real(eps) or not 0.0 < eps <= MAX_EPS:
        raise ValueError(f"eps (the NUFFT's relative tolerance) must lie in (0, {MAX_EPS:g}], got {eps!r}: "
                         "finufft's error grows fast beyond it (0.2 % at 1e-2, 16 % at 0.1 on a 24^3 grid)")
    if not isinstance(single, bool):
        raise ValueError(f"single must be true or false, got {single!r}")
    if single and eps < 1e-5:
        raise ValueError(f"single-precision NUFFT needs eps >= 1e-5, got eps={eps!r}")
    low, high = UPSAMPFAC_RANGE
    if upsampfac is not None and (not is_real(upsampfac) or not low <= upsampfac <= high):
        raise ValueError(f"upsampfac (the NUFFT's oversampling factor) must be null (finufft's choice) or a number "
                         f"in [{low:g}, {high:g}] (finufft's range), got {upsampfac!r}")
    if nthreads is not None:
        whole_number("nthreads (NUFFT threads; null: as many as torch uses)", nthreads, 1)


class FourierOperator(DipOperator):
    """Dip transform of the box-voxel model by Fourier slices (see module docstring).

    Args:
        grid, directions, n_slabs: see :class:`~dipnet.operators.base.DipOperator`.
        bandwidth: highest frequency used, as a multiple of the slab Nyquist frequency
            ``1 / (2 delta)``; the kernel-tail truncation error falls with it.
        axis_boost: bandwidth factor for orientations within ``2 / N`` rad of a grid axis.
        eps: NUFFT tolerance (relative, in ``(0, MAX_EPS]``; float64 arithmetic unless ``single``, any input
            dtype). The adjoint is exact to rounding whatever ``eps``.
        nthreads: NUFFT threads (default: ``torch.get_num_threads()``, or 1 for tiny problems,
            where thread start-up costs more than it saves).
        upsampfac: the NUFFT's oversampling factor (``None``: finufft's choice, 2 for these
            tolerances). 1.25 with ``eps=1e-3`` makes a 240^3 transform with 5,760 orientations
            about 4x faster (3.8 s instead of 17 s on one busy core), at 1e-3 relative error.
        single: run the NUFFT (FFT and spreading) in single precision (complex64; the kernel
            weights, folding and slab FFTs stay float64). For ``eps >= 1e-5`` only; at 240^3
            with 5,760 orientations, ``eps=1e-3, upsampfac=1.25`` it makes a forward + adjoint
            1.65x faster (3.2 s instead of 5.2 s of one core; the NUFFTs alone 2.7 s instead of 4.7 s).
    """

    def __init__(self, grid: Grid, directions: torch.Tensor, n_slabs: int | None = None,
                 bandwidth: float = 4.0, axis_boost: float = 32.0, eps: float = 1e-6,
                 nthreads: int | None = None, upsampfac: float | None = None, single: bool = False) -> None:
        super().__init__(grid, directions, n_slabs)
        check_options(bandwidth, axis_boost, eps, nthreads, upsampfac, single)
        self.bandwidth, self.axis_boost = float(bandwidth), float(axis_boost)
        self.eps = float(eps)
        self.single = bool(single)
        self._complex = np.complex64 if self.single else np.complex128
        self.upsampfac = None if upsampfac is None else float(upsampfac)
        # to build the same operator on another grid
        self.options = {"bandwidth": self.bandwidth, "axis_boost": self.axis_boost, "eps": self.eps,
                        "upsampfac": self.upsampfac, "single": self.single}
        h, delta, d = grid.voxel_size, self.slab_thickness, grid.ndim
        support = grid.radius + (h * math.sqrt(d) + delta) / 2  # g_k vanishes beyond, mm
        self.period_slabs = math.ceil((support + grid.extent / 2) / delta) + 2  # M_T
        self.period = self.period_slabs * delta  # T, mm
        theta = self.directions.numpy()  # (K, d), (x, y[, z])
        # Within ~1/N rad of a grid axis the voxel heights are nearly a lattice, the spectrum
        # does not decay and the kernel tail matters: those few orientations get more frequencies.
        near_axis = np.abs(theta).max(axis=1) > math.cos(_AXIS_ANGLE / grid.n)
        band = np.where(near_axis, self.bandwidth * self.axis_boost, self.bandwidth)
        n_freq = np.ceil(band * self.period_slabs / 2).astype(np.int64) + 1  # n = 0 .. n_freq_k - 1
        k_of = np.repeat(np.arange(self.n_orientations), n_freq)  # (P,) orientation of each point
        n_of = np.arange(k_of.size) - np.repeat(np.cumsum(n_freq) - n_freq, n_freq)  # (P,) frequency index
        omega = n_of / self.period  # 1/mm
        th = theta[k_of]  # (P, d)
        # NUFFT points: 2 pi w h theta per axis, in volume axis order ([z, y, x] -> reversed theta).
        pts = 2 * np.pi * h * omega[:, None] * th[:, ::-1]
        self._points = [np.ascontiguousarray(np.remainder(p + np.pi, 2 * np.pi) - np.pi) for p in pts.T]
        # Voxel centres are (m + offset) h for finufft mode m (m = i - N//2); slab j at c_0 + j delta.
        offset = 0.5 - (grid.n % 2) * 0.5
        phase = 2 * np.pi * omega * (-h * offset * th.sum(1) - grid.extent / 2 + delta / 2)
        kernel = np.prod(np.sinc(h * th * omega[:, None]), axis=1) * h**d * delta * np.sinc(delta * omega)
        multiplicity = np.where(n_of == 0, 1.0, 2.0)  # the +-n pair of a real signal
        self._weights = kernel * multiplicity / self.period * np.exp(1j * phase)  # (P,) complex
        self._fold = k_of * self.period_slabs + n_of % self.period_slabs  # (P,) into (K, M_T)
        work = math.prod(grid.shape) + self._weights.size
        self.nthreads = int(nthreads or (torch.get_num_threads() if work > _SERIAL_LIMIT else 1))
        self._plan: finufft.Plan | None = None

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_plan"] = None  # finufft plans hold C memory; rebuilt lazily
        return state

    # ------------------------------------------------------------------ linear steps
    def _nufft(self) -> finufft.Plan:
        if self._plan is None:
            extra = {} if self.upsampfac is None else {"upsampfac": self.upsampfac}
            plan = finufft.Plan(2, self.grid.shape, n_trans=1, eps=self.eps, isign=-1,
                                dtype=np.dtype(self._complex).name, nthreads=self.nthreads, **extra)
            plan.setpts(*(p.astype(self._complex(0).real.dtype) for p in self._points))
            self._plan = plan
        return self._plan

    def _forward_np(self, vol: np.ndarray) -> np.ndarray:
        """One volume ``(*shape)`` float64 -> profiles ``(K, M)`` float64."""
        spectrum = self._nufft().execute(vol.astype(self._complex)) * self._weights
        size = self.n_orientations * self.period_slabs
        folded = (np.bincount(self._fold, spectrum.real, size) + 1j * np.bincount(self._fold, spectrum.imag, size))
        series = np.fft.ifft(folded.reshape(self.n_orientations, self.period_slabs), axis=1) * self.period_slabs
        return np.ascontiguousarray(series[:, :self.n_slabs].real)

    def _adjoint_np(self, prof: np.ndarray) -> np.ndarray:
        """Exact transpose of :meth:`_forward_np`: ``(K, M)`` float64 -> ``(*shape)`` float64."""
        padded = np.zeros((self.n_orientations, self.period_slabs), dtype=np.complex128)
        padded[:, :self.n_slabs] = prof
        folded = np.fft.fft(padded, axis=1).reshape(-1)
        spectrum = (folded[self._fold] * np.conj(self._weights)).astype(self._complex)
        return self._nufft().execute_adjoint(spectrum).real.astype(np.float64)

    def _transform(self, x: torch.Tensor, transpose: bool) -> torch.Tensor:
        step = self._adjoint_np if transpose else self._forward_np
        data = x.detach().to(torch.float64).numpy()
        out = np.stack([step(np.ascontiguousarray(item)) for item in data])
        return torch.from_numpy(out).to(x.dtype)

    # ------------------------------------------------------------------ DipOperator
    def _forward(self, volume: torch.Tensor) -> torch.Tensor:
        return _FourierApply.apply(volume, self, False)

    def _adjoint(self, profiles: torch.Tensor) -> torch.Tensor:
        return _FourierApply.apply(profiles, self, True)
