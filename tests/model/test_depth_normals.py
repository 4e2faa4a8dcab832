"""depth_normals against analytic surfaces: planes (exact), a sphere (to the pixel's angle), an
occlusion edge, the opacity rule and the orientation."""

import torch

from garmentnerf.conventions import camera_rays, orbit_camera
from garmentnerf.model.depth_normals import depth_normals


def _rays(size: int = 48):
    """(size, size, 3) origins and unit directions of a camera looking at the character's centre."""
    camera = orbit_camera(30.0, 10.0, 2.5, target=(0.0, 0.0, 0.9), width=size, height=size)
    return camera_rays(camera, dtype=torch.float64)


def _plane_depth(origins, directions, point, normal):
    """Distance along each ray to the plane through ``point`` with ``normal``."""
    point, normal = torch.tensor(point, dtype=torch.float64), torch.tensor(normal, dtype=torch.float64)
    normal = normal / normal.norm()
    return ((point - origins) @ normal) / (directions @ normal), normal


def test_a_plane_gets_its_normal_facing_the_camera_at_every_pixel():
    origins, directions = _rays()
    for sign in (1.0, -1.0):  # the plane's normal given either way round: the result faces the camera
        depth, normal = _plane_depth(origins, directions, (0.0, 0.0, 0.9), (sign * 0.3, sign * -0.8, sign * 0.2))
        out = depth_normals(depth, torch.ones_like(depth), origins, directions)
        facing = normal if float((normal * directions).sum(-1).mean()) < 0 else -normal
        torch.testing.assert_close(out.permute(1, 2, 0), facing.expand_as(origins), atol=1e-9, rtol=0)


def test_a_sphere_gets_its_radial_normal_to_the_pixel_angle():
    origins, directions = _rays(64)
    centre, radius = torch.tensor([0.0, 0.0, 0.9], dtype=torch.float64), 0.4
    # first intersection of each ray with the sphere
    oc = origins - centre
    b = (oc * directions).sum(-1)
    disc = b ** 2 - ((oc ** 2).sum(-1) - radius ** 2)
    hit = disc > 0
    depth = torch.where(hit, -b - disc.clamp_min(0).sqrt(), torch.zeros_like(b))
    out = depth_normals(depth, hit.double(), origins, directions).permute(1, 2, 0)
    truth = (origins + depth[..., None] * directions - centre) / radius
    error = torch.rad2deg(torch.acos((out * truth).sum(-1).clamp(-1, 1)))
    # A chord between two points of a sphere is perpendicular to the mean of their normals, so the normal
    # of two one-sided chords lies within the turn of the true normal from the pixel to its neighbours.
    turn = torch.zeros_like(error)
    for step in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        neighbour, neighbour_hit = torch.roll(truth, step, (0, 1)), torch.roll(hit, step, (0, 1))
        angle = torch.rad2deg(torch.acos((truth * neighbour).sum(-1).clamp(-1, 1)))
        turn = torch.maximum(turn, torch.where(neighbour_hit, angle, torch.zeros_like(angle)))
    inner = hit & (-(truth * directions).sum(-1) > 0.5)  # away from the limb, where it turns edge-on
    assert int(inner.sum()) > 300
    assert bool((error[inner] <= turn[inner]).all())
    assert 0.5 < float(turn[inner].max()) < 10.0  # the bound is a few degrees, not vacuous
    assert float(out[~hit].abs().max()) == 0.0


def test_an_occlusion_edge_keeps_each_surface_its_own_normal():
    origins, directions = _rays()
    near, n_near = _plane_depth(origins, directions, (0.0, -0.3, 0.9), (0.5, -0.7, 0.1))
    far, n_far = _plane_depth(origins, directions, (0.0, 0.4, 0.9), (-0.2, -0.9, -0.3))
    left = torch.zeros_like(near, dtype=torch.bool)
    left[:, :20] = True
    depth = torch.where(left, near, far)
    assert float((far[:, 19:21] - near[:, 19:21]).min()) > 0.3  # a real jump at the edge
    out = depth_normals(depth, torch.ones_like(depth), origins, directions).permute(1, 2, 0)

    def facing(n):
        return n if float((n * directions).sum(-1).mean()) < 0 else -n

    torch.testing.assert_close(out[left], facing(n_near).expand(int(left.sum()), 3), atol=1e-9, rtol=0)
    torch.testing.assert_close(out[~left], facing(n_far).expand(int((~left).sum()), 3), atol=1e-9, rtol=0)


def test_pixels_without_opacity_or_a_neighbour_get_no_normal():
    origins, directions = _rays(16)
    depth, _ = _plane_depth(origins, directions, (0.0, 0.0, 0.9), (0.0, -1.0, 0.0))
    opacity = torch.zeros_like(depth)
    opacity[5, 5] = 1.0  # alone: no neighbour along rows or columns
    opacity[10, 3:9] = 1.0  # a row: neighbours along it, none across it
    opacity[12, 12] = 0.49  # under the threshold
    out = depth_normals(depth, opacity, origins, directions)
    assert float(out.abs().max()) == 0.0
    opacity[11, 3:9] = 1.0  # a second row: now both directions have a neighbour
    out = depth_normals(depth, opacity, origins, directions)
    assert torch.all(out[:, 10:12, 3:9].norm(dim=0) > 0.999)
    assert int((out.norm(dim=0) > 0).sum()) == 12
