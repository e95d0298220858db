"""A frame's camera images -> the N x 3 x H x W tensor LCPR reads, on the device the network runs on.

Three decoders (``ModelConfig.decode``):

- ``pil``: the released pipeline (PIL decode, PIL bilinear resize): :func:`.camera.camera_tensor`.
- ``turbo``: JPEGs decoded at a reduced size by libjpeg-turbo (:mod:`.decode`), in two pool
  threads (the decoders and torch release the GIL). On the CPU, above :data:`SMALL_RESIZE` output
  values (the released 256 x 704 input), each image is resized by torch's antialiased bilinear
  filter (the filter PIL's bilinear resize applies) on uint8 pixels and normalised straight into
  its slot of the output by the pool thread that decoded it, so both cores stay busy and each
  image is still in cache; the frame's range image follows in the pool (:meth:`CameraPreprocessor.start`).
  Smaller inputs (the bundled 64 x 192) are resized in one batch on one thread after the decodes.
  For a GPU the decoded pixels are uploaded as uint8 and resized there.
- ``nvjpeg``: on a CUDA device, JPEGs uploaded as bytes and decoded by nvJPEG
  (``torchvision.io.decode_jpeg(..., device="cuda")``, all six in one batch), resized and
  normalised there; the pixels never come back to the CPU.
- ``auto``: nvjpeg where the network runs on CUDA and torchvision's GPU decoder imports, else turbo.

Raw arrays (already decoded ``Image`` messages) skip the decoder and are uploaded as uint8.
A camera whose image cannot be used (corrupt or truncated bytes, a bad array) leaves its slot
zero, as a missing camera does; :meth:`CameraPreprocessor.__call__` says which and why.
"""
from __future__ import annotations

import ctypes
import logging
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from ...errors import InputShapeError, InvalidValueError, LcprError
from .camera import IMAGENET_MEAN, IMAGENET_STD, CameraInput, camera_tensor
from .decode import is_jpeg, jpeg_size, rgb_array

log = logging.getLogger(__name__)

DECODERS = ("auto", "pil", "turbo", "nvjpeg")
#: CPU resizes with at most this many output values run in one batch on one thread: a parallel region costs
#: more than it saves on such small tensors, and on a loaded machine it waits for a descheduled thread
#: (docs/keyframe_pipeline.md, "Preprocessing"); larger inputs are resized image by image in the pool
#: threads that decoded them
SMALL_RESIZE = 1 << 20
#: what :meth:`CameraPreprocessor.start` returns: call it for (N x 3 x H x W, {slot: why it was left out},
#: what ``beside`` returned or None)
Finish = Callable[[], "tuple[torch.Tensor, dict[int, str], torch.Tensor | None]"]
_POOL: ThreadPoolExecutor | None = None


def _pool() -> ThreadPoolExecutor:
    global _POOL
    if _POOL is None:
        _POOL = ThreadPoolExecutor(max_workers=2, thread_name_prefix="lcpr-decode", initializer=_one_omp_thread)
    return _POOL


def _one_omp_thread() -> None:
    """Pool-thread start-up: this thread's torch ops run on one OpenMP thread.

    Two pool threads, one image each, already fill two cores; a team per op would only contend.
    OpenMP keeps the team size per thread, so the caller's and every other thread's settings stay as
    they are (``torch.set_num_threads`` would also change the size new threads start with). Where
    torch's OpenMP symbols cannot be found (another parallel backend) the ops keep torch's default.
    """
    torch.get_num_threads()  # torch's own per-thread set-up runs now, so it does not undo the line below later
    try:
        setter = getattr(ctypes.CDLL(None), "omp_set_num_threads", None)
    except (OSError, TypeError):  # no handle on the process's own symbols (not Linux or macOS)
        setter = None
    if setter is not None:
        setter(1)


def nvjpeg_decoder() -> tuple[Callable[..., Any] | None, str]:
    """torchvision's GPU JPEG decoder, or None and why it cannot be used here."""
    try:
        from torchvision.io import ImageReadMode, decode_jpeg  # type: ignore[import-not-found, unused-ignore]
    except Exception as err:  # torchvision absent, or built for another torch ('operator ... does not exist')
        return None, f"torchvision.io.decode_jpeg does not import ({type(err).__name__}: {err})"

    def decode(data: list[torch.Tensor], device: torch.device) -> list[torch.Tensor]:
        return list(decode_jpeg(data, mode=ImageReadMode.RGB, device=device))

    return decode, ""


def resolve_decoder(decoder: str, device: str) -> str:
    """What ``decoder`` means on ``device``: ``auto`` -> nvjpeg on CUDA where it imports, else turbo."""
    if decoder not in DECODERS:
        raise InvalidValueError(f"decode={decoder!r}; accepted: {', '.join(DECODERS)}")
    cuda = torch.device(device).type == "cuda"
    if decoder == "nvjpeg" and not cuda:
        raise InvalidValueError(f"decode='nvjpeg' needs model.device cuda (got {device!r}); accepted on the CPU: "
                                "auto, pil, turbo")
    if decoder != "auto":
        return decoder
    if cuda and nvjpeg_decoder()[0] is not None:
        return "nvjpeg"
    return "turbo"


@contextmanager
def _one_thread(on: bool) -> Iterator[None]:
    """torch's intra-op threads set to one inside (when ``on``), restored after."""
    threads = torch.get_num_threads()
    if not on or threads == 1:
        yield
        return
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def _stack(pixels: list[torch.Tensor]) -> torch.Tensor:
    """3 x h x w images of one size -> B x 3 x h x w; CPU views of h x w x 3 arrays stay channels-last."""
    if pixels[0].device.type == "cpu" and pixels[0].stride()[0] == 1:
        return torch.from_numpy(np.stack([p.permute(1, 2, 0).numpy() for p in pixels])).permute(0, 3, 1, 2)
    return torch.stack(pixels)


def _raise_first(failed: dict[int, str], strict: bool) -> None:
    if failed and strict:
        k = min(failed)
        raise InputShapeError(f"camera {k}: {failed[k]}")


class CameraPreprocessor:
    """N camera images -> (N x 3 x H x W float32 on ``device``, {slot: why its image was left out})."""

    def __init__(self, *, size: tuple[int, int], device: str = "cpu", decoder: str = "auto",
                 draft: bool = False) -> None:
        self.size = (int(size[0]), int(size[1]))
        self.device = torch.device(device)
        self.decoder = resolve_decoder(decoder, device)
        self.draft = draft  # PIL draft mode, for decoder 'pil' only (ModelConfig.fast_decode)
        self._nvjpeg: Callable[..., Any] | None = None
        if self.decoder == "nvjpeg":
            self._nvjpeg, why = nvjpeg_decoder()
            if self._nvjpeg is None:
                raise InvalidValueError(f"decode='nvjpeg': {why}; accepted: auto, turbo, pil")
        std = torch.tensor(IMAGENET_STD, dtype=torch.float32)
        mean = torch.tensor(IMAGENET_MEAN, dtype=torch.float32)
        # (x / 255 - mean) / std as one multiply-add: x * scale + bias
        self._scale = (1.0 / (255.0 * std)).view(1, 3, 1, 1).to(self.device)
        self._bias = (-mean / std).view(1, 3, 1, 1).to(self.device)
        #: images nvJPEG refused and the CPU decoded instead (counted, warned once)
        self.nvjpeg_fallbacks = 0
        #: when a list, the CPU paths append (stage, thread CPU seconds): each decode, each resize (benchmarks)
        self.profile: list[tuple[str, float]] | None = None

    def __call__(self, images: Sequence[CameraInput | None], *, strict: bool = False
                 ) -> tuple[torch.Tensor, dict[int, str]]:
        """``strict``: raise on the first unusable image instead of leaving its slot zero."""
        out, failed, _ = self.start(images, strict=strict)()
        return out, failed

    def start(self, images: Sequence[CameraInput | None], *, strict: bool = False,
              beside: Callable[[], torch.Tensor] | None = None) -> Finish:
        """Begin preprocessing ``images`` (and run ``beside``, the frame's range image); the returned function
        waits for the result: :meth:`__call__`'s and what ``beside`` returned.

        On the CPU with ``turbo`` at a size above :data:`SMALL_RESIZE` the images go to the pool one by one
        and ``beside`` after them, so the two pool threads keep both cores busy to the end; the other paths
        finish here.
        """
        if not images:
            raise InputShapeError("no camera images given; expected one per camera (6 for nuScenes)")
        if self.decoder == "turbo" and self.device.type == "cpu" and not self._small(len(images)):
            return self._start_fused(images, strict=strict, beside=beside)
        if self.decoder == "pil":
            out, failed = self._pil(images, strict=strict)
        else:
            pixels, failed = self.decode(images)
            _raise_first(failed, strict)
            out = self.assemble(pixels, len(images))
        done = out, failed, None if beside is None else beside()
        return lambda: done

    def many(self, frames: Sequence[Sequence[CameraInput | None]]) -> tuple[torch.Tensor, list[dict[int, str]]]:
        """Several frames' images, N slots each -> (B x N x 3 x H x W on ``device``, per frame {slot: why its
        image was left out}). Decoded together (nvJPEG: every frame's JPEGs in one call; turbo: in the pool),
        then resized and normalised frame by frame, which bounds the float copies to one frame's images.
        Each frame's result equals :meth:`__call__`'s."""
        if not frames or not frames[0]:
            raise InputShapeError("no frames or no camera images given; expected one image slot per camera")
        count = len(frames[0])
        if any(len(images) != count for images in frames):
            raise InputShapeError(f"frames with {sorted({len(images) for images in frames})} camera slots; "
                                  f"every frame of a batch needs the same number ({count})")
        out = torch.empty(len(frames), count, 3, *self.size, device=self.device)  # B x N x 3 x H x W
        failed: list[dict[int, str]] = [{} for _ in frames]
        if self.decoder == "pil":
            for b, images in enumerate(frames):
                out[b], failed[b] = self(images)
            return out, failed
        pixels, bad = self.decode([image for images in frames for image in images])
        for k, why in bad.items():
            failed[k // count][k % count] = why
        per_frame: list[dict[int, torch.Tensor]] = [{} for _ in frames]
        for k, value in pixels.items():
            per_frame[k // count][k % count] = value
        for b, frame_pixels in enumerate(per_frame):
            out[b] = self.assemble(frame_pixels, count)
        return out, failed

    def _small(self, count: int) -> bool:
        """Whether ``count`` images at this size are under :data:`SMALL_RESIZE`: decoded in the pool, then resized
        in one batch on one thread (six tiny per-image resizes cost more in dispatch than they share out)."""
        return count * 3 * self.size[0] * self.size[1] <= SMALL_RESIZE

    def _start_fused(self, images: Sequence[CameraInput | None], *, strict: bool,
                     beside: Callable[[], torch.Tensor] | None) -> Finish:
        """Each image decoded, resized and normalised into its slot of one N x 3 x H x W tensor by a pool thread."""
        out = torch.empty(len(images), 3, *self.size)  # N x 3 x H x W; slots without an image are zeroed below
        slots = [k for k, img in enumerate(images) if img is not None]
        jobs: dict[int, Future[str | None]] = {}
        extra: Future[torch.Tensor] | None = None
        if len(slots) > 1:
            pool = _pool()
            jobs = {k: pool.submit(self._fill, images[k], out[k]) for k in slots}
            extra = None if beside is None else pool.submit(beside)

        def finish() -> tuple[torch.Tensor, dict[int, str], torch.Tensor | None]:
            failed: dict[int, str] = {}
            for k in slots:
                why = jobs[k].result() if jobs else self._fill(images[k], out[k])
                if why is not None:
                    failed[k] = why
            for k in range(len(images)):
                if k in failed or images[k] is None:
                    out[k].zero_()
            _raise_first(failed, strict)
            if extra is not None:
                return out, failed, extra.result()
            return out, failed, None if beside is None else beside()

        return finish

    def _fill(self, image: CameraInput | None, slot: torch.Tensor) -> str | None:
        """One image -> its 3 x H x W slot (decoded, resized, normalised); why it cannot be used, else None."""
        assert image is not None
        profile = self.profile
        t0 = time.thread_time() if profile is not None else 0.0
        try:
            arr = rgb_array(image, self.size)  # h x w x 3 uint8
        except InputShapeError as err:
            return str(err)
        t1 = time.thread_time() if profile is not None else 0.0
        pixels = torch.from_numpy(arr).permute(2, 0, 1).unsqueeze(0)  # 1 x 3 x h x w, a channels-last view
        if tuple(pixels.shape[-2:]) != self.size:  # torch's fast uint8 path, rounded as PIL's resize
            pixels = F.interpolate(pixels, size=self.size, mode="bilinear", antialias=True, align_corners=False)
        slot.copy_(pixels[0])
        slot.mul_(self._scale[0]).add_(self._bias[0])
        if profile is not None:
            profile += [("decode", t1 - t0), ("resize + normalise", time.thread_time() - t1)]
        return None

    def decode(self, images: Sequence[CameraInput | None]) -> tuple[dict[int, torch.Tensor], dict[int, str]]:
        """The decoding stage: slot -> 3 x h x w uint8 pixels (on the GPU after nvJPEG, else CPU views of
        h x w x 3 arrays), and slot -> why an image could not be used."""
        failed: dict[int, str] = {}
        pixels: dict[int, torch.Tensor] = {}
        if self.decoder == "nvjpeg":
            cpu_slots = self._decode_on_device(images, pixels, failed)
        else:
            cpu_slots = [k for k, img in enumerate(images) if img is not None]
        todo = [img for k in cpu_slots if (img := images[k]) is not None]  # cpu_slots name no missing camera
        arrays = _pool().map(self._rgb, todo) if len(todo) > 1 else map(self._rgb, todo)
        for k, arr in zip(cpu_slots, arrays, strict=True):
            if isinstance(arr, InputShapeError):
                failed[k] = str(arr)
            else:
                pixels[k] = torch.from_numpy(arr).permute(2, 0, 1)  # a channels-last view, no copy
        return pixels, failed

    def assemble(self, pixels: dict[int, torch.Tensor], count: int) -> torch.Tensor:
        """The resize-and-normalise stage: decoded slots -> ``count`` x 3 x H x W on the device, absent slots 0."""
        if self.profile is not None:
            t0 = time.thread_time()
            out = self._assemble(pixels, count)
            self.profile.append(("resize + normalise", time.thread_time() - t0))
            return out
        return self._assemble(pixels, count)

    def _assemble(self, pixels: dict[int, torch.Tensor], count: int) -> torch.Tensor:
        groups: dict[tuple[Any, ...], list[int]] = {}  # one resize per image size and place
        for k in sorted(pixels):
            groups.setdefault((pixels[k].device, *pixels[k].shape), []).append(k)
        if len(groups) == 1 and len(pixels) == count:  # the usual frame: every camera, one size
            return self._resize_normalise(_stack([pixels[k] for k in range(count)]))
        out = torch.zeros(count, 3, *self.size, device=self.device)
        for slots in groups.values():
            out[slots] = self._resize_normalise(_stack([pixels[k] for k in slots]))
        return out

    def _rgb(self, image: CameraInput) -> np.ndarray | InputShapeError:
        profile = self.profile
        t0 = time.thread_time() if profile is not None else 0.0
        try:
            return rgb_array(image, self.size)
        except InputShapeError as err:
            return err
        finally:
            if profile is not None:
                profile.append(("decode", time.thread_time() - t0))

    def _resize_normalise(self, batch: torch.Tensor) -> torch.Tensor:
        """B x 3 x h x w uint8 -> B x 3 x H x W float32 on the device: antialiased bilinear (PIL's filter),
        ImageNet statistics."""
        if batch.device != self.device:  # decoded on the CPU for a GPU: upload the uint8 pixels, resize there
            batch = batch.contiguous().to(self.device, non_blocking=True)
        if batch.device.type == "cpu":
            with _one_thread(batch.shape[0] * batch.shape[1] * self.size[0] * self.size[1] <= SMALL_RESIZE):
                if tuple(batch.shape[-2:]) != self.size:  # torch's fast uint8 path, rounded as PIL's resize
                    batch = F.interpolate(batch.contiguous(memory_format=torch.channels_last), size=self.size,
                                          mode="bilinear", antialias=True, align_corners=False)
                return batch.contiguous().float().mul_(self._scale).add_(self._bias)
        if tuple(batch.shape[-2:]) != self.size:
            batch = F.interpolate(batch.float(), size=self.size, mode="bilinear", antialias=True,
                                  align_corners=False).round_().clamp_(0, 255)
        return batch.float().mul_(self._scale).add_(self._bias)

    def _decode_on_device(self, images: Sequence[CameraInput | None], pixels: dict[int, torch.Tensor],
                          failed: dict[int, str]) -> list[int]:
        """nvJPEG for the JPEG slots (all in one call); returns the slots left for the CPU decoder."""
        assert self._nvjpeg is not None
        jpegs, cpu = [], []
        for k, img in enumerate(images):
            if img is None:
                continue
            if isinstance(img, (bytes, bytearray, memoryview)) and is_jpeg(img):
                try:
                    jpeg_size(img)  # refuses truncated files, as the CPU decoders do
                except InputShapeError as err:
                    failed[k] = str(err)
                    continue
                jpegs.append(k)
            else:
                cpu.append(k)
        if not jpegs:
            return cpu
        data = [torch.frombuffer(bytearray(images[k]), dtype=torch.uint8) for k in jpegs]  # type: ignore[arg-type]
        try:
            decoded = self._nvjpeg(data, self.device)
        except RuntimeError:
            decoded = []
            for k, d in zip(jpegs, data, strict=True):  # one by one: which camera's bytes were refused
                try:
                    decoded.extend(self._nvjpeg([d], self.device))
                except RuntimeError as err:  # the CPU decoder then says whether the bytes are bad
                    self.nvjpeg_fallbacks += 1
                    if self.nvjpeg_fallbacks in (1, 10, 100, 1000):
                        log.warning("LCPR: nvJPEG refused camera %d's image (%s); decoded on the CPU instead "
                                    "(%d image(s) so far)", k, str(err).splitlines()[0], self.nvjpeg_fallbacks)
                    cpu.append(k)
                    decoded.append(None)
        for k, img in zip(jpegs, decoded, strict=True):
            if img is not None:
                pixels[k] = img
        return cpu

    def _pil(self, images: Sequence[CameraInput | None], *, strict: bool) -> tuple[torch.Tensor, dict[int, str]]:
        failed: dict[int, str] = {}
        out = torch.zeros(len(images), 3, *self.size)
        for k, img in enumerate(images):
            if img is None:
                continue
            try:
                out[k] = camera_tensor(img, size=self.size, fast_decode=self.draft)
            except LcprError as err:
                if strict:
                    raise InputShapeError(f"camera {k}: {err}") from err
                failed[k] = str(err)
        return out.to(self.device), failed
