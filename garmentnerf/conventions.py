"""The project's conventions, defined once: world axes, cameras, pixels, the canonical pose.

Every pass (OpenGL and torch) and every data loader goes through this module, so that a 3D
point, a ray and a pixel mean the same thing everywhere.

World
    Right-handed, metres, **Z up**. At rest the character stands on the plane z = 0 and faces
    **-Y** (a camera at (0, -3, 1) looking at +Y sees its front). These are the axes of the
    anny body model; DeepMimic (Y-up) and SMPL (Y-up) data are converted on load.

Cameras (OpenCV convention)
    ``x_cam = R @ x_world + t``; camera looks along +z_cam, +x_cam is image right, +y_cam is
    image down. ``K`` maps camera coordinates to continuous pixel coordinates where the centre
    of pixel (column c, row r) is at (c, r), as OpenCV calibrations (ZJU-MoCap included)
    assume. Images are arrays ``(H, W, C)`` with row 0 at the top.

Canonical pose
    ``b_o`` (the paper's canonical body point) lives on the *template* body: the average body
    shape (all shape coefficients zero) in the rest pose of the rig (all joint rotations zero;
    an A-pose for anny, a T-pose for SMPL). Using the template rather than the posed subject's
    own rest shape keeps ``b_o`` identical across body shapes, so features learned on one shape
    transfer to another.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

UP_AXIS = np.array([0.0, 0.0, 1.0])
FORWARD_AXIS = np.array([0.0, -1.0, 0.0])  # the direction a character at rest faces

#: Default clip planes (metres) for GL passes; a camera may override them.
DEFAULT_NEAR = 0.01
DEFAULT_FAR = 100.0


@dataclass(frozen=True)
class Camera:
    """A pinhole camera in the OpenCV convention.

    Attributes:
        K: (3, 3) intrinsics, pixel centres at integer coordinates.
        R: (3, 3) world-to-camera rotation.
        t: (3,) world-to-camera translation (``x_cam = R x + t``).
        width, height: image size in pixels.
        near, far: clip distances along the optical axis, metres.
    """

    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    width: int
    height: int
    near: float = DEFAULT_NEAR
    far: float = DEFAULT_FAR

    def __post_init__(self) -> None:
        for name, shape in (("K", (3, 3)), ("R", (3, 3)), ("t", (3,))):
            value = np.asarray(getattr(self, name), dtype=np.float64)
            if value.shape != shape:
                raise ValueError(f"camera {name} must have shape {shape}, got {value.shape}")
            if not np.all(np.isfinite(value)):
                raise ValueError(f"camera {name} contains NaN or Inf")
            object.__setattr__(self, name, value)
        if self.width < 1 or self.height < 1:
            raise ValueError(f"camera image size must be positive, got {self.width}x{self.height}")
        if not (0 < self.near < self.far):
            raise ValueError(f"camera needs 0 < near < far, got near={self.near} far={self.far}")

    @property
    def center(self) -> np.ndarray:
        """(3,) camera centre in world coordinates."""
        return -self.R.T @ self.t

    def world_to_camera(self) -> np.ndarray:
        """(4, 4) world-to-camera matrix."""
        m = np.eye(4)
        m[:3, :3] = self.R
        m[:3, 3] = self.t
        return m

    def gl_projection(self) -> np.ndarray:
        """(4, 4) matrix from OpenCV camera coordinates to GL clip coordinates.

        Built so that rasterising with it puts the point the intrinsics map to continuous pixel
        (u, v) at the centre of pixel (u, v) of the framebuffer, with framebuffer row 0 at the
        *top* of the image. Reading the framebuffer back row by row therefore gives an image in
        this module's layout with no flip. Depth maps [near, far] to NDC z in [-1, 1].

        The y flip mirrors triangle winding, so passes that cull faces must flip their
        front-face setting; the project's passes do not cull.
        """
        return gl_projection_from_intrinsics(self.K, self.width, self.height, self.near, self.far)

    def scaled(self, factor: float) -> "Camera":
        """The same camera at ``factor`` times the resolution (pixel centres stay consistent)."""
        w = max(1, round(self.width * factor))
        h = max(1, round(self.height * factor))
        return self.resized(w, h)

    def resized(self, width: int, height: int) -> "Camera":
        """The same view at another resolution: continuous pixel coordinates scale by W'/W, H'/H
        about the image corner (-0.5, -0.5)."""
        sx, sy = width / self.width, height / self.height
        K = self.K.copy()
        K[0, 0] *= sx
        K[0, 1] *= sx
        K[1, 1] *= sy
        K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
        K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
        return Camera(K, self.R, self.t, width, height, self.near, self.far)

    def cropped(self, x0: int, y0: int, width: int, height: int) -> "Camera":
        """The pixels ``[x0, x0 + width) x [y0, y0 + height)`` of this camera as a camera of their
        own: pixel (c, r) of the crop is pixel (c + x0, r + y0) of this one (the principal point
        moves by (-x0, -y0)); the window may extend past the image."""
        K = self.K.copy()
        K[0, 2] -= int(x0)
        K[1, 2] -= int(y0)
        return Camera(K, self.R, self.t, int(width), int(height), self.near, self.far)


def gl_projection_from_intrinsics(K: np.ndarray, width: int, height: int, near: float, far: float) -> np.ndarray:
    """(4, 4) OpenCV-camera -> GL-clip matrix; see :meth:`Camera.gl_projection`.

    Continuous pixel u in [-0.5, W - 0.5] maps to NDC x in [-1, 1]; pixel v in [-0.5, H - 0.5]
    maps to NDC y in [-1, 1] (so image row 0 is framebuffer row 0). With w_clip = z_cam:
        x_ndc = (2 (fx x/z + s y/z + cx) + 1) / W - 1
        y_ndc = (2 (fy y/z + cy) + 1) / H - 1
        z_ndc = (f + n)/(f - n) - 2 f n / ((f - n) z)
    """
    fx, s, cx = K[0, 0], K[0, 1], K[0, 2]
    fy, cy = K[1, 1], K[1, 2]
    P = np.zeros((4, 4))
    P[0, 0] = 2.0 * fx / width
    P[0, 1] = 2.0 * s / width
    P[0, 2] = (2.0 * cx + 1.0) / width - 1.0
    P[1, 1] = 2.0 * fy / height
    P[1, 2] = (2.0 * cy + 1.0) / height - 1.0
    P[2, 2] = (far + near) / (far - near)
    P[2, 3] = -2.0 * far * near / (far - near)
    P[3, 2] = 1.0
    return P


def look_at(eye, target, up=UP_AXIS) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera (R (3, 3), t (3,)) for a camera at ``eye`` looking at ``target``.

    Image "up" is the projection of ``up``; raises if ``eye == target`` or the view is parallel
    to ``up``.
    """
    eye = np.asarray(eye, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    forward = target - eye
    norm = np.linalg.norm(forward)
    if norm < 1e-12:
        raise ValueError("look_at: eye and target coincide")
    z = forward / norm
    x = np.cross(z, np.asarray(up, dtype=np.float64))  # image right = forward x up
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("look_at: view direction is parallel to the up vector")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)  # image down
    R = np.stack([x, y, z])
    return R, -R @ eye


def intrinsics_from_fov(width: int, height: int, fov_y_deg: float) -> np.ndarray:
    """(3, 3) intrinsics with square pixels and the principal point at the image centre."""
    if not (0.0 < fov_y_deg < 180.0):
        raise ValueError(f"vertical field of view must be in (0, 180) degrees, got {fov_y_deg}")
    fy = 0.5 * height / np.tan(np.deg2rad(fov_y_deg) / 2.0)
    return np.array([[fy, 0.0, (width - 1) / 2.0], [0.0, fy, (height - 1) / 2.0], [0.0, 0.0, 1.0]])


def orbit_camera(azimuth_deg: float, elevation_deg: float, radius: float, target=(0.0, 0.0, 0.9),
                 width: int = 512, height: int = 512, fov_y_deg: float = 40.0, near: float = DEFAULT_NEAR,
                 far: float = DEFAULT_FAR) -> Camera:
    """A camera on a sphere around ``target``.

    Azimuth 0 is in front of the character (on the -Y side, looking at +Y); azimuth increases
    counter-clockwise seen from above, so 90 deg is on the +X side, the character's left.
    """
    az, el = np.deg2rad(azimuth_deg), np.deg2rad(elevation_deg)
    target = np.asarray(target, dtype=np.float64)
    offset = radius * np.array([np.sin(az) * np.cos(el), -np.cos(az) * np.cos(el), np.sin(el)])
    R, t = look_at(target + offset, target)
    return Camera(intrinsics_from_fov(width, height, fov_y_deg), R, t, width, height, near, far)


def pixel_centers(height: int, width: int, dtype=torch.float32, device=None) -> torch.Tensor:
    """(H, W, 2) continuous pixel coordinates (u, v) of every pixel centre: (c, r)."""
    v, u = torch.meshgrid(torch.arange(height, dtype=dtype, device=device),
                          torch.arange(width, dtype=dtype, device=device), indexing="ij")
    return torch.stack([u, v], dim=-1)


def camera_rays(camera: Camera, dtype=torch.float32, device=None) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays through every pixel centre.

    Returns:
        origins (H, W, 3) world-space camera centre, repeated.
        directions (H, W, 3) world-space unit directions.
    """
    uv = pixel_centers(camera.height, camera.width, torch.float64, device)
    Kinv = torch.as_tensor(np.linalg.inv(camera.K), dtype=torch.float64, device=device)
    pix = torch.cat([uv, torch.ones_like(uv[..., :1])], dim=-1)
    d_cam = pix @ Kinv.T
    Rt = torch.as_tensor(camera.R, dtype=torch.float64, device=device)
    d_world = d_cam @ Rt  # R^T d for each row
    d_world = d_world / d_world.norm(dim=-1, keepdim=True)
    origin = torch.as_tensor(camera.center, dtype=torch.float64, device=device).expand_as(d_world)
    return origin.to(dtype), d_world.to(dtype)


def project_points(camera: Camera, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Project world points ``(N, 3)`` to continuous pixel coordinates.

    Returns:
        uv (N, 2) pixel coordinates (centre of pixel (c, r) at (c, r)).
        depth (N,) camera-space z (positive in front of the camera).
    """
    R = torch.as_tensor(camera.R, dtype=points.dtype, device=points.device)
    t = torch.as_tensor(camera.t, dtype=points.dtype, device=points.device)
    K = torch.as_tensor(camera.K, dtype=points.dtype, device=points.device)
    x_cam = points @ R.T + t
    z = x_cam[:, 2]
    pix = x_cam @ K.T
    uv = pix[:, :2] / z.unsqueeze(-1)
    return uv, z
