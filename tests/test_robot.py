"""Robot model: URDF parsing, FK against hand-computed transforms, geometry, decimation, errors."""

from __future__ import annotations

import math
from pathlib import Path

import fast_simplification
import numpy as np
import pytest
import torch
import trimesh

from roboseg.errors import RobotModelError
from roboseg.robot import RobotModel, default_urdf_path, load_robot
from roboseg.robot.meshes import MIN_DECIMATED_FACES, cluster_vertices, decimation_target
from roboseg.robot.transforms import origin_matrix, rpy_matrix

MED7_JOINTS = [f"A{i}" for i in range(1, 8)]
MED7_FRAMES = [f"link_{i}" for i in range(8)] + ["link_ee"]


def write_urdf(folder: Path, body: str, name: str = "toy.urdf") -> Path:
    path = folder / name
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(f'<?xml version="1.0"?>\n<robot name="toy">\n{body}\n</robot>\n')
    return path


def link(name: str, geometry: str = "", origin: str = "", tag: str = "visual") -> str:
    if not geometry:
        return f'<link name="{name}"/>'
    return f'<link name="{name}"><{tag}>{origin}<geometry>{geometry}</geometry></{tag}></link>'


def joint(
    name: str,
    parent: str,
    child: str,
    jtype: str = "revolute",
    xyz: str = "0 0 0",
    rpy: str = "0 0 0",
    axis: str = "0 0 1",
    lower: float = -1.0,
    upper: float = 1.0,
) -> str:
    return (
        f'<joint name="{name}" type="{jtype}"><origin xyz="{xyz}" rpy="{rpy}"/>'
        f'<parent link="{parent}"/><child link="{child}"/><axis xyz="{axis}"/>'
        f'<limit lower="{lower}" upper="{upper}" effort="1" velocity="1"/></joint>'
    )


BOX = '<box size="0.1 0.1 0.1"/>'
BAD_BOX = '<box size="1 -1 1"/>'
CAPSULE = '<capsule radius="1"/>'


def two_link_urdf(folder: Path) -> Path:
    """base -(j1: z-axis, 0.5 up)- l1 -(j2: z-axis, 1 along x, roll 90°)- l2 -(fixed 0.2 x)- tip."""
    return write_urdf(
        folder,
        "\n".join(
            [
                link("base", BOX),
                link("l1", BOX),
                link("l2", BOX),
                link("tip"),
                joint("j1", "base", "l1", xyz="0 0 0.5"),
                joint("j2", "l1", "l2", xyz="1 0 0", rpy=f"{math.pi / 2} 0 0"),
                joint("tool", "l2", "tip", jtype="fixed", xyz="0.2 0 0"),
            ]
        ),
    )


# --- pure maths -------------------------------------------------------------------------------


def test_rpy_matrix_matches_hand_computed_rotations() -> None:
    rx90 = [[1, 0, 0], [0, 0, -1], [0, 1, 0]]
    rz90 = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    np.testing.assert_allclose(rpy_matrix([math.pi / 2, 0, 0]), rx90, atol=1e-12)
    np.testing.assert_allclose(rpy_matrix([0, 0, math.pi / 2]), rz90, atol=1e-12)
    # roll then yaw about fixed axes: Rz(90) @ Rx(90); x -> y, y -> z, z -> x
    np.testing.assert_allclose(
        rpy_matrix([math.pi / 2, 0, math.pi / 2]), [[0, 0, 1], [1, 0, 0], [0, 1, 0]], atol=1e-12
    )
    T = origin_matrix([1, 2, 3], [0, math.pi / 2, 0])  # pitch 90° maps x onto -z
    np.testing.assert_allclose(T @ [1, 0, 0, 1], [1, 2, 2, 1], atol=1e-12)


def test_cluster_vertices_merges_cells_and_drops_collapsed_faces() -> None:
    # a unit square (two triangles) plus a sliver whose corners 1 and 4 share a 0.5-wide cell
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [1.2, 0.1, 0]], dtype=np.float64)
    f = np.array([[0, 1, 2], [0, 2, 3], [1, 4, 2], [2, 1, 0]])
    merged, faces = cluster_vertices(v, f, 0.5)
    assert len(merged) == 4
    np.testing.assert_allclose(merged[faces[0, 1]], [1.1, 0.05, 0.0])  # mean of 1 and 4
    # the sliver collapses, the reversed duplicate of face 0 goes: the square remains
    assert faces.shape == (2, 3)
    np.testing.assert_allclose(merged[faces].reshape(-1, 3)[:, :2].sum(), 6.15)


def test_decimation_target_counts() -> None:
    assert decimation_target(1000, 0.95) == 50
    assert decimation_target(1000, 0.0) == 1000
    assert decimation_target(100, 0.95) == MIN_DECIMATED_FACES  # floor for small shapes
    assert decimation_target(12, 0.95) == 12  # a box is never decimated


# --- kinematics -------------------------------------------------------------------------------


def test_two_link_fk_with_rpy_origin_matches_hand_computation(tmp_path: Path) -> None:
    robot = load_robot(two_link_urdf(tmp_path), dtype=torch.float64)
    assert robot.frame_names == ["base", "l1", "l2", "tip"]
    assert robot.joint_names == ["j1", "j2"] and robot.dof == 2
    q = torch.tensor([[math.pi / 2, math.pi / 2], [0.0, 0.0]], dtype=torch.float64)
    T = robot.frame_transforms(q)
    assert T.shape == (2, 4, 4, 4)
    # q = (90°, 90°): T_base_l2 = Trans(0,0,.5) Rz90 Trans(1,0,0) Rx90 Rz90
    np.testing.assert_allclose(T[0, 1, :3, 3], [0, 0, 0.5], atol=1e-12)
    np.testing.assert_allclose(T[0, 2, :3, 3], [0, 1, 0.5], atol=1e-12)
    np.testing.assert_allclose(T[0, 2, :3, :3], [[0, 0, 1], [0, -1, 0], [1, 0, 0]], atol=1e-12)
    np.testing.assert_allclose(T[0, 3, :3, 3], [0, 1, 0.7], atol=1e-12)
    # q = 0: l2 frame is rolled 90° about x at (1, 0, 0.5); tip 0.2 further along x
    np.testing.assert_allclose(T[1, 2, :3, :3], [[1, 0, 0], [0, 0, -1], [0, 1, 0]], atol=1e-12)
    np.testing.assert_allclose(T[1, 3, :3, 3], [1.2, 0, 0.5], atol=1e-12)
    # link_transforms are the frames with geometry
    assert robot.link_names == ["base", "l1", "l2"]
    torch.testing.assert_close(robot.link_transforms(torch.zeros(2)), T[1:2, :3])


def test_fk_is_differentiable(tmp_path: Path) -> None:
    robot = load_robot(two_link_urdf(tmp_path), dtype=torch.float64)
    q = torch.tensor([0.3, -0.7], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: robot.frame_transforms(x)[:, -1], (q,))
    robot.posed_vertices(q).sum().backward()
    assert q.grad is not None and torch.all(q.grad.abs() > 0)


def test_fk_agrees_with_pytorch_kinematics_on_random_rpy_chain(tmp_path: Path) -> None:
    pk = pytest.importorskip("pytorch_kinematics")
    rng = np.random.default_rng(0)
    kinds = ["revolute", "prismatic", "continuous", "revolute", "revolute", "prismatic"]
    parts = [link(f"l{i}", BOX) for i in range(7)]
    for i, kind in enumerate(kinds):
        xyz, rpy, axis = rng.normal(size=3) * 0.3, rng.uniform(-3, 3, 3), rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        fmt = " ".join
        parts.append(
            joint(
                f"j{i}",
                f"l{i}",
                f"l{i + 1}",
                kind,
                xyz=fmt(f"{v:.5f}" for v in xyz),
                rpy=fmt(f"{v:.5f}" for v in rpy),
                axis=fmt(f"{v:.8f}" for v in axis),
            )
        )
    urdf = write_urdf(tmp_path, "\n".join(parts))
    robot = load_robot(urdf, dtype=torch.float64)
    chain = pk.build_serial_chain_from_urdf(urdf.read_bytes(), "l6").to(dtype=torch.float64)
    q = robot.random_joints(8, torch.Generator().manual_seed(1), margin=0.0)
    expected = chain.forward_kinematics(q, end_only=True).get_matrix()
    torch.testing.assert_close(robot.frame_transforms(q)[:, -1], expected, atol=1e-5, rtol=0)


def test_six_dof_toy_with_mixed_joints_and_tool_frames(tmp_path: Path) -> None:
    """Any similar URDF: other names, continuous + prismatic joints, geometry-free side frames."""
    cyl = '<cylinder radius="0.05" length="0.3"/>'
    names = ["waist", "shoulder", "elbow", "slide", "wrist", "flange"]
    links = ["base", "upper", "lower", "carriage", "hand", "tool"]
    parts = [link(n, cyl) for n in links] + [link("tcp"), link("camera_mount")]
    for i, jname in enumerate(names):
        jtype = {"slide": "prismatic", "flange": "continuous"}.get(jname, "revolute")
        parts.append(
            joint(
                jname,
                links[i - 1] if i else "world",
                links[i],
                jtype,
                xyz="0 0 0.3",
                axis="0 1 0" if i % 2 else "0 0 1",
                lower=-0.5 * (i + 1),
                upper=0.25 * (i + 1),
            )
        )
    parts[0:0] = [link("world")]
    parts.append(joint("to_tcp", "tool", "tcp", "fixed", xyz="0 0 0.1"))
    parts.append(joint("to_cam", "upper", "camera_mount", "fixed", xyz="0.1 0 0"))
    robot = load_robot(write_urdf(tmp_path, "\n".join(parts)))
    assert robot.name == "toy" and robot.root_link == "world"
    assert robot.joint_names == names and robot.dof == 6
    assert robot.frame_names == ["world", *links, "tcp", "camera_mount"]
    assert robot.link_names == links
    assert robot.lower[5].item() == pytest.approx(-math.pi)  # continuous: [-pi, pi]
    assert robot.upper[3].item() == pytest.approx(1.0)
    # prismatic 'slide' (axis y) moves everything after it; zero config stacks 0.3 m per joint
    q = torch.zeros(6)
    q[3] = 0.2
    T = robot.frame_transforms(q)[0]
    np.testing.assert_allclose(T[robot.frame_names.index("tcp"), :3, 3], [0, 0.2, 1.9], atol=1e-6)
    np.testing.assert_allclose(
        T[robot.frame_names.index("camera_mount"), :3, 3], [0.1, 0, 0.6], atol=1e-6
    )
    g = torch.Generator().manual_seed(0)
    qs = robot.random_joints(500, g, margin=0.1)
    span = robot.upper - robot.lower
    assert qs.shape == (500, 6)
    assert torch.all(qs >= robot.lower + 0.1 * span) and torch.all(qs <= robot.upper - 0.1 * span)
    assert torch.all(qs.std(0) > 0.2 * span / math.sqrt(12))
    mesh = robot.mesh(qs[0])
    assert isinstance(mesh, trimesh.Trimesh) and len(mesh.faces) == len(robot.faces)


def test_joint_vector_checks_and_reordering(default_robot: RobotModel) -> None:
    r = default_robot
    assert r.check_joints(torch.zeros(7)).shape == (1, 7)
    assert r.check_joints(np.zeros((3, 7))).shape == (3, 7)
    values = torch.arange(7.0)
    shuffled = ["A3", "A1", "A7", "A2", "A5", "A4", "A6"]
    out = r.joints_from_names(shuffled, values)
    torch.testing.assert_close(out, torch.tensor([1.0, 3, 0, 5, 4, 6, 2]))
    assert r.joints_from_names(shuffled, values.repeat(2, 1)).shape == (2, 7)
    with pytest.raises(RobotModelError, match=r"unknown \['B9'\], missing \['A7'\]"):
        r.joints_from_names([*MED7_JOINTS[:6], "B9"], values)
    with pytest.raises(RobotModelError, match="expected 7 joint values"):
        r.posed_vertices(torch.zeros(6))
    with pytest.raises(RobotModelError, match="expected 7 joint values"):
        r.frame_transforms(torch.zeros(2, 3, 7))
    with pytest.raises(RobotModelError, match=r"non-finite values for joints \['A4'\]"):
        r.check_joints(torch.tensor([0, 0, 0, float("nan"), 0, 0, 0]))


# --- geometry ---------------------------------------------------------------------------------


def cube_mesh(path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    trimesh.creation.box(extents=(1, 1, 1)).export(path)
    return path


def link_vertices(robot: RobotModel, name: str) -> np.ndarray:
    return robot.vertices[robot.vertex_link == robot.link_names.index(name)].numpy()


def test_primitives_mesh_scale_and_visual_origin(tmp_path: Path) -> None:
    cube_mesh(tmp_path / "meshes" / "cube.stl")
    cube_mesh(tmp_path / "meshes" / "cube.obj")
    parts = [
        link("box", '<box size="0.2 0.4 0.6"/>', '<origin xyz="1 0 0"/>'),
        link("cyl", '<cylinder radius="0.1" length="0.5"/>', f'<origin rpy="{math.pi / 2} 0 0"/>'),
        link("ball", '<sphere radius="0.3"/>', '<origin xyz="0 0 2"/>'),
        link("stl", '<mesh filename="meshes/cube.stl" scale="0.1 0.2 0.3"/>'),
        link("obj", f'<mesh filename="file://{tmp_path}/meshes/cube.obj" scale="2"/>'),
    ]
    names = ["box", "cyl", "ball", "stl", "obj"]
    parts += [joint(f"j{i}", names[i - 1], names[i]) for i in range(1, 5)]
    robot = load_robot(write_urdf(tmp_path, "\n".join(parts)), dtype=torch.float64)
    assert robot.link_names == names
    v = link_vertices(robot, "box")
    np.testing.assert_allclose(v.min(0), [0.9, -0.2, -0.3], atol=1e-9)
    np.testing.assert_allclose(v.max(0), [1.1, 0.2, 0.3], atol=1e-9)
    v = link_vertices(robot, "cyl")  # rolled 90°: the cylinder's axis lies along y
    np.testing.assert_allclose(np.abs(v).max(0), [0.1, 0.25, 0.1], atol=1e-9)
    r = np.linalg.norm(v[:, [0, 2]], axis=1)
    assert np.all((np.abs(r - 0.1) < 1e-9) | (r < 1e-9))  # rim or cap centre
    v = link_vertices(robot, "ball")
    np.testing.assert_allclose(np.linalg.norm(v - [0, 0, 2], axis=1), 0.3, atol=1e-9)
    np.testing.assert_allclose(np.ptp(link_vertices(robot, "stl"), axis=0), [0.1, 0.2, 0.3])
    np.testing.assert_allclose(np.ptp(link_vertices(robot, "obj"), axis=0), [2, 2, 2])
    assert robot.faces.shape[1] == 3 and int(robot.faces.max()) == len(robot.vertices) - 1
    # posed vertices: the box link is the root, so it does not move
    posed = robot.posed_vertices(torch.full((4,), 0.3))
    torch.testing.assert_close(posed[0, robot.vertex_link == 0], robot.vertices[:8])


def test_dae_mesh_through_trimesh(tmp_path: Path) -> None:
    pytest.importorskip("collada", reason="DAE needs pycollada")
    cube_mesh(tmp_path / "cube.dae")
    parts = [
        link("a", '<mesh filename="cube.dae" scale="0.5 0.5 0.5"/>'),
        link("b", BOX),
        joint("j", "a", "b"),
    ]
    robot = load_robot(write_urdf(tmp_path, "\n".join(parts)), dtype=torch.float64)
    np.testing.assert_allclose(np.ptp(link_vertices(robot, "a"), axis=0), [0.5, 0.5, 0.5])


def test_package_uri_is_found_in_parent_folders(tmp_path: Path) -> None:
    cube_mesh(tmp_path / "my_robot_description" / "meshes" / "cube.stl")
    body = "\n".join(
        [
            link("a", '<mesh filename="package://my_robot_description/meshes/cube.stl"/>'),
            link("b", BOX),
            joint("j", "a", "b"),
        ]
    )
    urdf = write_urdf(tmp_path / "my_robot_description" / "urdf", body)
    robot = load_robot(urdf)
    assert len(link_vertices(robot, "a")) == 8
    # the package folder may also sit beside an ancestor of the URDF
    moved = write_urdf(tmp_path / "ws" / "robots", body)
    (tmp_path / "ws" / "my_robot_description").symlink_to(tmp_path / "my_robot_description")
    assert len(load_robot(moved).faces) == len(robot.faces)


def test_visual_or_collision_geometry_with_fallback(tmp_path: Path) -> None:
    both = (
        '<link name="a"><visual><geometry><box size="1 1 1"/></geometry></visual>'
        '<collision><geometry><sphere radius="0.5"/></geometry></collision></link>'
    )
    only_collision = link("b", '<box size="2 2 2"/>', tag="collision")
    urdf = write_urdf(tmp_path, "\n".join([both, only_collision, joint("j", "a", "b")]))
    visual, collision = load_robot(urdf), load_robot(urdf, geometry="collision")
    assert len(link_vertices(visual, "a")) == 8  # box
    assert len(link_vertices(collision, "a")) > 100  # tessellated sphere
    for robot in (visual, collision):  # 'b' has collision geometry only: used in both cases
        np.testing.assert_allclose(np.ptp(link_vertices(robot, "b"), axis=0), [2, 2, 2])
    with pytest.raises(RobotModelError, match="geometry must be one of"):
        load_robot(urdf, geometry="inertial")


def test_decimation_reaches_target_and_hits_cache(tmp_path: Path, monkeypatch) -> None:
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.1)  # 5120 faces
    sphere.export(tmp_path / "ball.stl")
    parts = [link("a", '<mesh filename="ball.stl"/>'), link("b", BOX), joint("j", "a", "b")]
    urdf = write_urdf(tmp_path, "\n".join(parts))
    cache = tmp_path / "cache"
    full = load_robot(urdf, cache_dir=cache)
    small = full.decimated(0.9)
    n_ball = int((full.vertex_link[full.faces[:, 0]] == 0).sum())
    n_small = int((small.vertex_link[small.faces[:, 0]] == 0).sum())
    assert n_ball == 5120 and n_small == pytest.approx(512, rel=0.05)
    assert int((small.vertex_link[small.faces[:, 0]] == 1).sum()) == 12  # tiny box kept
    assert small.faces.max() < len(small.vertices)  # no dangling indices
    assert len(torch.unique(small.faces)) == len(small.vertices)  # no unused vertices
    radius = small.vertices[small.vertex_link == 0].norm(dim=1)
    assert torch.all((radius > 0.095) & (radius < 0.105))  # still the same sphere
    entries = sorted((cache / "decimated").glob("*.npz"))
    assert len(entries) == 1  # the box is below the decimation floor, never simplified

    def refuse(*args, **kwargs):
        raise AssertionError("cache miss: simplify was called")

    monkeypatch.setattr(fast_simplification, "simplify", refuse)
    again = load_robot(urdf, reduction=0.9, cache_dir=cache)
    torch.testing.assert_close(again.vertices, small.vertices)
    assert torch.equal(again.faces, small.faces)
    torch.testing.assert_close(
        again.frame_transforms(torch.ones(1)), full.frame_transforms(torch.ones(1))
    )
    with pytest.raises(AssertionError, match="cache miss"):
        load_robot(urdf, reduction=0.8, cache_dir=cache)
    with pytest.raises(RobotModelError, match="reduction must be in"):
        full.decimated(1.0)


def test_decimation_cache_location_from_environment(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setenv("ROBOSEG_CACHE", str(tmp_path / "envcache"))
    load_robot(None, reduction=0.5)
    assert len(list((tmp_path / "envcache" / "decimated").glob("*.npz"))) > 0


def test_to_changes_dtype_and_keeps_results(default_robot: RobotModel) -> None:
    r64 = default_robot.to(dtype=torch.float64)
    assert r64.vertices.dtype == torch.float64 and default_robot.vertices.dtype == torch.float32
    q = default_robot.random_joints(3, torch.Generator().manual_seed(1))
    assert q.dtype == torch.float32
    torch.testing.assert_close(
        r64.posed_vertices(q).float(), default_robot.posed_vertices(q), atol=1e-5, rtol=0
    )


# --- the default robot and the LBR Med 7 --------------------------------------------------------


def test_default_robot_needs_no_files(default_robot: RobotModel) -> None:
    r = default_robot
    assert default_urdf_path().is_file() and r.urdf_path == default_urdf_path()
    assert r.joint_names == MED7_JOINTS and r.frame_names == MED7_FRAMES
    assert r.link_names == MED7_FRAMES[:-1] and r.root_link == "link_0"
    np.testing.assert_allclose(r.upper.numpy(), [2.96706, 2.094395] * 3 + [3.054326], rtol=1e-6)
    torch.testing.assert_close(r.lower, -r.upper)
    assert 5_000 < len(r.faces) <= 20_000
    assert set(r.vertex_link.tolist()) == set(range(8))
    posed = r.posed_vertices(torch.zeros(7))[0]
    # upright: the flange top sits at the end-effector height, the arm is ~14 cm wide
    assert posed[:, 2].max().item() == pytest.approx(1.266, abs=1e-4)
    assert posed[:, 2].min().item() == pytest.approx(0.0, abs=1e-6)
    assert posed[:, :2].abs().max().item() < 0.13


@pytest.mark.lbr
def test_med7_zero_and_bent_configurations_hand_computed(lbr_urdf: Path) -> None:
    r = load_robot(lbr_urdf)
    assert r.joint_names == MED7_JOINTS and r.frame_names == MED7_FRAMES
    ee = r.frame_names.index("link_ee")
    # zero config: joint z offsets 0.1475 + 0.1925 + 0.2075 + 0.1925 + 0.2075 + 0.1925 + 0.091,
    # plus 0.035 for link_ee; the y offsets cancel
    height = 0.1475 + 0.1925 + 0.2075 + 0.1925 + 0.2075 + 0.1925 + 0.091 + 0.035
    q = torch.zeros(2, 7)
    q[1, 1] = math.pi / 2  # A2 (axis y at z = 0.34) tips everything above it onto +x
    T = r.frame_transforms(q)
    np.testing.assert_allclose(T[0, ee, :3, 3], [0, 0, height], atol=1e-6)
    np.testing.assert_allclose(T[1, ee, :3, 3], [height - 0.34, 0, 0.34], atol=1e-6)
    np.testing.assert_allclose(T[1, ee, :3, :3], [[0, 0, 1], [0, 1, 0], [-1, 0, 0]], atol=1e-6)
    # visual origins put each STL back where it was authored (base frame at zero config)
    posed = r.posed_vertices(torch.zeros(7))[0]
    for i, name in enumerate(r.link_names):
        stl = trimesh.load(lbr_urdf.parent / "meshes" / f"{name}.stl")
        block = posed[r.vertex_link == i].numpy()
        np.testing.assert_allclose(block.min(0), stl.bounds[0], atol=1e-5)
        np.testing.assert_allclose(block.max(0), stl.bounds[1], atol=1e-5)


@pytest.mark.lbr
def test_default_robot_has_med7_kinematics(lbr_urdf: Path, default_robot: RobotModel) -> None:
    med7 = load_robot(lbr_urdf, reduction=0.95)
    torch.testing.assert_close(med7.lower, default_robot.lower)
    torch.testing.assert_close(med7.upper, default_robot.upper)
    q = med7.random_joints(16, torch.Generator().manual_seed(3))
    torch.testing.assert_close(
        med7.frame_transforms(q), default_robot.frame_transforms(q), atol=1e-5, rtol=0
    )


@pytest.mark.lbr
def test_med7_decimation_by_paper_reduction(lbr_urdf: Path) -> None:
    full = load_robot(lbr_urdf)
    small = full.decimated(0.95)
    ratio = len(small.faces) / len(full.faces)
    assert abs(ratio - 0.05) < 0.01 * 0.05  # 5 % of the faces kept, within 1 % of the target
    assert small.frame_names == full.frame_names
    q = full.random_joints(9, torch.Generator().manual_seed(0))
    a, b = full.posed_vertices(q), small.posed_vertices(q)
    assert b.shape == (9, len(small.vertices), 3)
    # same envelope within 2 cm: quadric decimation of link_4 to 5 % moves its support in
    # some directions by up to ~1.7 cm (~1.6 cm already when it stalled at 20 %)
    for i in range(9):
        np.testing.assert_allclose(b[i].min(0).values, a[i].min(0).values, atol=2e-2)
        np.testing.assert_allclose(b[i].max(0).values, a[i].max(0).values, atol=2e-2)


# --- bad input ----------------------------------------------------------------------------------


def test_missing_mesh_file_names_the_path(tmp_path: Path) -> None:
    parts = [link("a", '<mesh filename="meshes/nope.stl"/>'), link("b", BOX), joint("j", "a", "b")]
    with pytest.raises(RobotModelError, match=r"link 'a'.*not found: .*meshes/nope\.stl"):
        load_robot(write_urdf(tmp_path, "\n".join(parts)))
    parts[0] = link("a", '<mesh filename="package://ghost_pkg/m.stl"/>')
    with pytest.raises(RobotModelError, match="package 'ghost_pkg' not found"):
        load_robot(write_urdf(tmp_path, "\n".join(parts)))


def test_non_serial_tree_is_refused(tmp_path: Path) -> None:
    parts = [
        link("base", BOX),
        link("left", BOX),
        link("right", BOX),
        joint("jl", "base", "left"),
        joint("jr", "base", "right"),
    ]
    with pytest.raises(RobotModelError, match=r"link 'base' branches into \['left', 'right'\]"):
        load_robot(write_urdf(tmp_path, "\n".join(parts)))


def test_no_movable_joints_is_refused(tmp_path: Path) -> None:
    parts = [link("a", BOX), link("b", BOX), joint("j", "a", "b", jtype="fixed")]
    with pytest.raises(RobotModelError, match="no movable joints"):
        load_robot(write_urdf(tmp_path, "\n".join(parts)))


@pytest.mark.parametrize(
    ("body", "message"),
    [
        ("<link name='a'><visual>", "malformed or unsafe XML"),
        (f"{link('a', BOX)}{link('b', BOX)}{joint('j', 'a', 'ghost')}", "unknown link 'ghost'"),
        (
            f"{link('a', BOX)}{link('b', BOX)}{joint('j', 'a', 'b', jtype='floating')}",
            "joint 'j': unsupported type 'floating'",
        ),
        (
            f"{link('a', BOX)}{link('b', BOX)}{joint('j', 'a', 'b', axis='0 0 0')}",
            "joint 'j': <axis xyz> must not be zero",
        ),
        (
            f"{link('a', BOX)}{link('b', BOX)}{joint('j', 'a', 'b', xyz='1 2 x')}",
            r"joint 'j' <origin xyz>: expected 3 finite numbers, got '1 2 x'",
        ),
        (
            f"{link('a', BOX)}{link('b', BOX)}{joint('j', 'a', 'b', lower=1, upper=0)}",
            "lower 1.0 > upper 0.0",
        ),
        (
            f"{link('a', BAD_BOX)}{link('b', BOX)}{joint('j', 'a', 'b')}",
            "link 'a' <visual>: <box> dimensions must be positive",
        ),
        (
            f"{link('a', CAPSULE)}{link('b', BOX)}{joint('j', 'a', 'b')}",
            "unsupported geometry <capsule>",
        ),
        (
            f"{link('a', BOX)}{link('b', BOX)}{link('c', BOX)}{joint('j', 'a', 'b')}",
            r"expected one root link, found \['a', 'c'\]",
        ),
        (
            f"{link('a', BOX)}{link('b', BOX)}{joint('j', 'a', 'b')}{joint('k', 'a', 'b')}",
            "link 'b' is the child of two joints",
        ),
    ],
)
def test_malformed_urdf_raises_one_clear_error(tmp_path: Path, body: str, message: str) -> None:
    urdf = write_urdf(tmp_path, body)
    with pytest.raises(RobotModelError, match=message) as info:
        load_robot(urdf)
    assert str(urdf) in str(info.value) and "\n" not in str(info.value)


def test_hostile_xml_entities_are_refused(tmp_path: Path) -> None:
    urdf = tmp_path / "laughs.urdf"
    urdf.write_text(
        '<?xml version="1.0"?><!DOCTYPE robot [<!ENTITY lol "lol">'
        '<!ENTITY lol2 "&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;">]>'
        '<robot name="&lol2;"><link name="a"/></robot>'
    )
    with pytest.raises(RobotModelError, match="malformed or unsafe XML"):
        load_robot(urdf)
    with pytest.raises(RobotModelError, match="URDF file not found"):
        load_robot(tmp_path / "absent.urdf")
