"""Hard rasteriser: hand-computed coverage and depth, a brute-force reference, batching, chunks."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

import roboseg.render.raster as raster
from roboseg.camera import Intrinsics, look_at
from roboseg.errors import CameraError
from roboseg.render import rasterize, render_hard

MED7 = Path("/work/shared/robots/lbr_med7/lbr_med7.urdf")


def _quad(z: float, half: float, offset: tuple[float, float] = (0.0, 0.0)) -> torch.Tensor:
    x, y = offset
    return torch.tensor(
        [
            [x - half, y - half, z],
            [x + half, y - half, z],
            [x + half, y + half, z],
            [x - half, y + half, z],
        ]
    )


QUAD_FACES = torch.tensor([[0, 1, 2], [0, 2, 3]])


def _reference(
    verts: torch.Tensor,
    faces: torch.Tensor,
    K: torch.Tensor,  # noqa: N803
    h: int,
    w: int,
    z_near: float,
    tile: int = 16,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Brute force in float64: every pixel centre of a tile against every projected triangle
    whose bounding box meets the tile (triangles are binned to tiles, not enumerated by pixel)."""
    v = verts.double()
    uv = (v @ K.double().T)[:, :2] / v[:, 2:3]
    tri, tz = uv[faces], v[faces, 2]  # [F, 3, 2], [F, 3]
    ok = (tz >= z_near).all(1)
    lo, hi = tri.amin(1), tri.amax(1)  # [F, 2]
    depth = torch.full((h, w), float("inf"), dtype=torch.float64)
    face_id = torch.full((h, w), -1, dtype=torch.int64)
    for v0 in range(0, h, tile):
        for u0 in range(0, w, tile):
            u1, v1 = min(u0 + tile, w), min(v0 + tile, h)
            hit = ok & (hi[:, 0] >= u0) & (lo[:, 0] <= u1 - 1) & (hi[:, 1] >= v0)
            hit &= lo[:, 1] <= v1 - 1
            ids = hit.nonzero().squeeze(1)
            if ids.numel() == 0:
                continue
            vv, uu = torch.meshgrid(
                torch.arange(v0, v1, dtype=torch.float64),
                torch.arange(u0, u1, dtype=torch.float64),
                indexing="ij",
            )
            pu, pv = uu.reshape(1, -1), vv.reshape(1, -1)
            p = tri[ids]  # [n, 3, 2]
            e = torch.stack(
                [  # edge function opposite corner 0, 1, 2 at every pixel centre [3, n, P]
                    (p[:, k, None, 0] - p[:, j, None, 0]) * (pv - p[:, j, None, 1])
                    - (p[:, k, None, 1] - p[:, j, None, 1]) * (pu - p[:, j, None, 0])
                    for j, k in ((1, 2), (2, 0), (0, 1))
                ]
            )
            area = e.sum(0)  # E_0 + E_1 + E_2 = twice the signed area, at every pixel
            inside = ((e >= 0).all(0) | (e <= 0).all(0)) & (area.abs() > 1e-9)
            inv_z = (e / area * (1.0 / tz[ids]).T[:, :, None]).sum(0)
            zmin, arg = torch.where(inside, 1.0 / inv_z, torch.inf).min(0)
            depth[v0:v1, u0:u1] = zmin.view(v1 - v0, u1 - u0)
            best = torch.where(torch.isfinite(zmin), ids[arg], -1)
            face_id[v0:v1, u0:u1] = best.view(v1 - v0, u1 - u0)
    return torch.isfinite(depth), depth, face_id


def test_triangle_coverage_by_pixel_centres_either_winding() -> None:
    K = torch.eye(3)
    # a triangle given directly in pixels (z = 1, K = I): (1, 1), (5, 1), (1, 5)
    v = torch.tensor([[[1.0, 1.0, 1.0], [5.0, 1.0, 1.0], [1.0, 5.0, 1.0]]])
    vv, uu = torch.meshgrid(torch.arange(8), torch.arange(8), indexing="ij")
    expected = (uu >= 1) & (vv >= 1) & (uu + vv <= 6)  # centres on the edges count
    for faces in (torch.tensor([[0, 1, 2]]), torch.tensor([[0, 2, 1]])):
        r = rasterize(v, faces, K, 8, 8)
        assert torch.equal(r.mask[0], expected)
        assert torch.equal(render_hard(v, faces, K, 8, 8)[0], expected)
        assert set(r.face_id[0].unique().tolist()) == {-1, 0}
    # shifted by half a pixel, (1.5, 1.5)-(5.5, 1.5)-(1.5, 5.5): the legs fall between centres
    r = rasterize(v + torch.tensor([0.5, 0.5, 0.0]), torch.tensor([[0, 1, 2]]), K, 8, 8)
    assert torch.equal(r.mask[0], (uu >= 2) & (vv >= 2) & (uu + vv <= 7))


def test_fronto_parallel_plane_depth_exact() -> None:
    K = torch.tensor([[10.0, 0.0, 4.5], [0.0, 10.0, 4.5], [0.0, 0.0, 1.0]])
    r = rasterize(_quad(2.0, 0.5)[None], QUAD_FACES, K, 10, 10)
    # u = 10·x/2 + 4.5 spans [2, 7] (inclusive: the edges hit pixel centres)
    expected = torch.zeros(10, 10, dtype=torch.bool)
    expected[2:8, 2:8] = True
    assert torch.equal(r.mask[0], expected)
    assert torch.all(r.depth[0][expected] == 2.0)
    assert torch.all(torch.isinf(r.depth[0][~expected]))
    assert torch.all(r.face_id[0][~expected] == -1)


def test_tilted_plane_depth_is_perspective_correct() -> None:
    K = torch.tensor([[60.0, 0.0, 31.5], [0.0, 60.0, 31.5], [0.0, 0.0, 1.0]], dtype=torch.float64)
    # plane z = 1 + 0.8·x, seen over x, y in [-0.5, 0.5]
    corners = torch.tensor(
        [[-0.5, -0.5], [0.5, -0.5], [0.5, 0.5], [-0.5, 0.5]], dtype=torch.float64
    )
    verts = torch.cat([corners, (1 + 0.8 * corners[:, :1])], dim=1)
    r = rasterize(verts[None], QUAD_FACES, K, 64, 64)
    assert r.mask.sum() > 1000
    v, u = r.mask[0].nonzero(as_tuple=True)
    ray_x = (u.double() - 31.5) / 60.0  # x/z of the pixel centre's ray
    z_expected = 1.0 / (1.0 - 0.8 * ray_x)  # z = 1 + 0.8·z·ray_x
    torch.testing.assert_close(r.depth[0][v, u].double(), z_expected, rtol=1e-6, atol=0.0)


def test_nearest_surface_wins_whatever_the_face_order() -> None:
    K = torch.tensor([[20.0, 0.0, 9.5], [0.0, 20.0, 9.5], [0.0, 0.0, 1.0]])
    far, near = _quad(2.0, 0.8), _quad(1.0, 0.2, (0.1, 0.0))
    for first, second in ((far, near), (near, far)):
        verts = torch.cat([first, second])[None]
        faces = torch.cat([QUAD_FACES, QUAD_FACES + 4])
        r = rasterize(verts, faces, K, 20, 20)
        near_faces = {0, 1} if first is near else {2, 3}
        near_mask = render_hard(near[None], QUAD_FACES, K, 20, 20)[0]
        assert near_mask.sum() > 0
        assert torch.all(r.depth[0][near_mask] == 1.0)
        assert set(r.face_id[0][near_mask].tolist()) <= near_faces
        assert torch.all(r.depth[0][r.mask[0] & ~near_mask] == 2.0)


def _robot_views(n: int, size: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Camera-frame vertices [n, V, 3] of a decimated robot in n random configurations, faces,
    and K; the Med 7 if present, else the built-in default arm."""
    from roboseg.robot import load_robot

    robot = load_robot(MED7 if MED7.is_file() else None, reduction=0.95)
    g = torch.Generator().manual_seed(7)
    q = robot.random_joints(n, generator=g)
    verts = robot.posed_vertices(q).double()
    centre = verts.mean(dim=(0, 1))
    eyes = centre + torch.tensor([1.1, 0.4, 0.3], dtype=torch.float64)
    eyes = eyes + 0.2 * torch.randn(n, 3, generator=g, dtype=torch.float64)
    T = look_at(eyes, centre.expand(n, 3), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    cam = verts @ T[:, :3, :3].transpose(1, 2) + T[:, None, :3, 3]
    intr = Intrinsics(0.9 * size, 0.9 * size, (size - 1) / 2, (size - 1) / 2, size, size)
    return cam.float(), robot.faces, intr.as_tensor()


def test_matches_brute_force_reference_on_robot() -> None:
    size = 256
    verts, faces, K = _robot_views(5, size)
    r = rasterize(verts, faces, K, size, size)
    for b in range(verts.shape[0]):
        mask, depth, face_id = _reference(verts[b], faces, K, size, size, 0.01)
        assert 0.05 < mask.float().mean() < 0.9  # the robot is well in view
        iou = (mask & r.mask[b]).sum() / (mask | r.mask[b]).sum()
        assert iou >= 0.98
        assert (mask != r.mask[b]).sum() <= 10  # only pixel centres within float error of edges
        both = mask & r.mask[b]
        rel = (r.depth[b][both].double() - depth[both]).abs() / depth[both]
        assert rel.max() < 1e-4
        assert (r.face_id[b][both] == face_id[both]).float().mean() > 0.99


def test_face_ids_consistent_with_depth() -> None:
    size = 96
    verts, faces, K = _robot_views(2, size)
    r = rasterize(verts, faces, K, size, size)
    for b in range(2):
        v, u = r.mask[b].nonzero(as_tuple=True)
        tri = verts[b].double()[faces[r.face_id[b][v, u]]]  # [N, 3, 3] camera frame
        # depth of that face's plane along the pixel centre's ray
        ray = torch.stack([u.double(), v.double(), torch.ones_like(u, dtype=torch.float64)], 1)
        ray = ray @ torch.linalg.inv(K.double()).T
        n = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], dim=1)
        t = (n * tri[:, 0]).sum(1) / (n * ray).sum(1)
        z = t * ray[:, 2]
        rel = (z - r.depth[b][v, u].double()).abs() / z
        assert rel.max() < 1e-3


def test_batch_equals_per_view_loop_and_silhouette_path() -> None:
    size = 64
    verts, faces, K = _robot_views(4, size)
    Kb = torch.stack([K * torch.tensor([[s], [s], [1.0]]) for s in (1.0, 0.8, 1.2, 1.0)])
    Kb[:, 2, 2] = 1.0
    batch = rasterize(verts, faces, Kb, size, size)
    hard = render_hard(verts, faces, Kb, size, size)
    assert torch.equal(hard, batch.mask)
    for b in range(4):
        one = rasterize(verts[b : b + 1], faces, Kb[b], size, size)
        assert torch.equal(one.mask[0], batch.mask[b])
        assert torch.equal(one.depth[0], batch.depth[b])
        assert torch.equal(one.face_id[0], batch.face_id[b])


def test_chunking_does_not_change_the_result(monkeypatch: pytest.MonkeyPatch) -> None:
    size = 64
    verts, faces, K = _robot_views(3, size)
    whole = rasterize(verts, faces, K, size, size)
    monkeypatch.setattr(raster, "PAIR_CHUNK", 97)
    monkeypatch.setattr(raster, "TRIANGLE_CHUNK", len(faces) // 2)  # one view per chunk
    chunked = rasterize(verts, faces, K, size, size)
    assert torch.equal(whole.depth, chunked.depth)
    assert torch.equal(whole.face_id, chunked.face_id)
    assert torch.equal(render_hard(verts, faces, K, size, size), whole.mask)


def test_near_plane_culling_and_errors() -> None:
    K = torch.tensor([[10.0, 0.0, 4.5], [0.0, 10.0, 4.5], [0.0, 0.0, 1.0]])
    quad = _quad(2.0, 0.5)
    crossing = quad.clone()
    crossing[1, 2] = 0.005  # a vertex of face 0 only, in front of z_near = 0.01: face 0 culled
    r = rasterize(crossing[None], QUAD_FACES, K, 10, 10)
    assert set(r.face_id.unique().tolist()) == {-1, 1}
    with pytest.raises(CameraError, match="behind the camera in view 1"):
        rasterize(torch.stack([quad, quad * torch.tensor([1.0, 1.0, -1.0])]), QUAD_FACES, K, 10, 10)
    with pytest.raises(CameraError, match="image size"):
        render_hard(quad[None], QUAD_FACES, K, 0, 10)
    with pytest.raises(CameraError, match="z_near"):
        rasterize(quad[None], QUAD_FACES, K, 10, 10, z_near=0.0)


def test_off_screen_mesh_renders_empty() -> None:
    K = torch.tensor([[10.0, 0.0, 4.5], [0.0, 10.0, 4.5], [0.0, 0.0, 1.0]])
    r = rasterize(_quad(2.0, 0.5, (5.0, 0.0))[None], QUAD_FACES, K, 10, 10)
    assert not r.mask.any() and torch.all(r.face_id == -1) and torch.all(torch.isinf(r.depth))
    assert r.depth.shape == (1, 10, 10) and r.depth.dtype == torch.float32


def test_inputs_requiring_grad_and_float64_are_accepted() -> None:
    K = torch.tensor([[10.0, 0.0, 4.5], [0.0, 10.0, 4.5], [0.0, 0.0, 1.0]], dtype=torch.float64)
    verts = _quad(2.0, 0.5)[None].double().requires_grad_(True)
    r = rasterize(verts, QUAD_FACES, K, 10, 10)
    assert not r.depth.requires_grad and r.depth.dtype == torch.float32
    assert int(r.mask.sum()) == 36 and torch.all(r.depth[r.mask] == 2.0)


def test_back_face_culling_keeps_closed_meshes_and_drops_faces_turned_away() -> None:
    import trimesh

    box = trimesh.creation.box(extents=(0.4, 0.3, 0.5))  # closed, outward counter-clockwise
    g = torch.Generator().manual_seed(3)
    eyes = torch.randn(4, 3, generator=g, dtype=torch.float64)
    eyes = 1.5 * eyes / eyes.norm(dim=1, keepdim=True)
    T = look_at(eyes, torch.zeros(4, 3, dtype=torch.float64))
    v = torch.as_tensor(box.vertices)
    cam = (v @ T[:, :3, :3].transpose(1, 2) + T[:, None, :3, 3]).float()
    faces = torch.as_tensor(box.faces)
    K = torch.tensor([[40.0, 0.0, 23.5], [0.0, 40.0, 23.5], [0.0, 0.0, 1.0]])
    full = rasterize(cam, faces, K, 48, 48)
    culled = rasterize(cam, faces, K, 48, 48, cull_back_faces=True)
    assert full.mask.sum() > 200
    assert torch.equal(full.depth, culled.depth) and torch.equal(full.mask, culled.mask)
    assert torch.equal(render_hard(cam, faces, K, 48, 48, cull_back_faces=True), full.mask)
    # a lone triangle, counter-clockwise seen from the camera (front) or clockwise (back)
    tri = torch.tensor([[[1.0, 1.0, 1.0], [1.0, 5.0, 1.0], [5.0, 1.0, 1.0]]])
    front, back = torch.tensor([[0, 1, 2]]), torch.tensor([[0, 2, 1]])
    assert rasterize(tri, front, torch.eye(3), 8, 8, cull_back_faces=True).mask.sum() == 15
    assert not render_hard(tri, back, torch.eye(3), 8, 8, cull_back_faces=True).any()


def _scenes() -> list[tuple[str, torch.Tensor, torch.Tensor, torch.Tensor, int, int]]:
    """(name, vertices [B, V, 3] camera frame, faces, K, height, width) that reach every path of
    the rasteriser: full robots near and far (one to many rows per triangle: row levels and
    tall triangles), partly off-screen and crossing the near plane, rows of a quad exactly on
    pixel rows (horizontal edges), degenerate faces and a vertex projecting to infinity."""
    from roboseg.robot import load_robot

    robot = load_robot(None)  # built-in arm, full mesh
    g = torch.Generator().manual_seed(11)
    q = robot.random_joints(3, generator=g)
    verts = robot.posed_vertices(q).double()
    centre = torch.tensor([0.1, 0.0, 0.5], dtype=torch.float64)
    eyes = centre + torch.tensor([[2.4, 0.5, 0.6], [0.9, -0.7, 0.3], [0.35, 0.2, 0.1]])
    T = look_at(eyes.double(), centre.expand(3, 3), torch.tensor([0.0, 0.0, 1.0]).double())
    arm = (verts @ T[:, :3, :3].transpose(1, 2) + T[:, None, :3, 3]).float()
    K = torch.tensor([[70.0, 0.0, 59.5], [0.0, 70.0, 44.5], [0.0, 0.0, 1.0]])
    quads = torch.stack([_quad(2.0, 0.5), _quad(1.0, 0.3, (0.2, -0.1))])
    odd = torch.tensor(  # a degenerate face, a face crossing z_near, one vertex at +inf in u
        [[[0.0, 0.0, 1.0], [0.2, 0.2, 1.0], [0.4, 0.4, 1.0], [3e38, 0.1, 1.0], [0.1, 0.3, 1.0],
          [-0.2, 0.1, 0.005]]]
    )
    odd_faces = torch.tensor([[0, 1, 2], [0, 3, 4], [1, 4, 5], [0, 4, 1]])
    Kq = torch.tensor([[10.0, 0.0, 4.5], [0.0, 10.0, 4.5], [0.0, 0.0, 1.0]])
    return [
        ("arm", arm, robot.faces, K, 90, 120),
        ("arm float64", arm.double(), robot.faces, K.double(), 37, 51),
        ("quads", quads, QUAD_FACES, Kq, 10, 10),
        ("odd", odd, odd_faces, Kq, 10, 10),
    ]


@pytest.mark.parametrize("cull", [False, True])
def test_same_pixels_as_the_reference_rasteriser_bit_for_bit(cull: bool) -> None:
    """The branch-free set-up and the row levels change how the spans are computed, not what
    they are: silhouettes, depths and face ids equal those of the previous implementation."""
    import raster_reference as ref

    for name, verts, faces, K, h, w in _scenes():
        hard = render_hard(verts, faces, K, h, w, cull_back_faces=cull)
        r = rasterize(verts, faces, K, h, w, cull_back_faces=cull)
        depth, face_id = ref.rasterize(verts, faces, K, h, w, cull_back_faces=cull)
        assert torch.equal(hard, ref.render_hard(verts, faces, K, h, w, cull_back_faces=cull)), name
        assert torch.equal(r.depth, depth), name
        assert torch.equal(r.face_id, face_id), name
        assert torch.equal(hard, r.mask), name


def test_edge_table_takes_the_selecting_path_for_non_finite_edges(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    paths: list[bool] = []
    edge_table = raster._edge_table

    def spy(*args: torch.Tensor) -> tuple[torch.Tensor, bool]:
        table, finite = edge_table(*args)
        paths.append(finite)
        return table, finite

    monkeypatch.setattr(raster, "_edge_table", spy)
    scenes = {name: s for name, *s in _scenes()}
    verts, faces, K, h, w = scenes["odd"]
    render_hard(verts, faces, K, h, w)
    verts, faces, K, h, w = scenes["quads"]
    render_hard(verts, faces, K, h, w)
    assert paths == [False, True]


def test_row_levels_cover_what_at_least_half_of_the_triangles_reach() -> None:
    levels = raster._dense_levels
    assert levels(torch.tensor([1, 1, 1, 1])) == 1
    assert levels(torch.tensor([2, 2, 1, 1])) == 2  # half have a second row
    assert levels(torch.tensor([3, 2, 1, 1])) == 2  # a quarter have a third
    assert levels(torch.tensor([40, 30, 20, 10])) == raster.MAX_LEVELS
