"""Loading meshes: every format in file coordinates, scene transforms, clear errors, winding repair."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from vehicle_pose.errors import EmptyMeshError, ModelError
from vehicle_pose.model.loading import load_mesh, oriented_faces, winding_consistent


@pytest.mark.parametrize("fmt", ["obj", "ply", "off", "stl", "glb"])
def test_every_format_loads_in_file_coordinates(tmp_path, fmt):
    box = trimesh.creation.box(extents=(2, 1, 0.5))
    box.apply_translation([10.0, -3.0, 1.0])
    path = tmp_path / f"box.{fmt}"
    box.export(path)
    mesh = load_mesh(path)
    assert mesh.n_faces == 12
    np.testing.assert_allclose(mesh.bounds, [[9, -3.5, 0.75], [11, -2.5, 1.25]], atol=1e-5)


def test_scene_transforms_are_applied(tmp_path):
    scene = trimesh.Scene()
    scene.add_geometry(trimesh.creation.box(extents=(1, 1, 1)),
                       transform=trimesh.transformations.translation_matrix([5, 0, 0]))
    path = tmp_path / "scene.glb"
    scene.export(path)
    assert load_mesh(path).bounds[0, 0] == pytest.approx(4.5)


def test_empty_and_missing_meshes_are_clear_errors(tmp_path):
    empty = tmp_path / "empty.obj"
    empty.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    with pytest.raises(EmptyMeshError):
        load_mesh(empty)
    with pytest.raises(ModelError):
        load_mesh(tmp_path / "missing.obj")
    garbage = tmp_path / "garbage.ply"
    garbage.write_bytes(b"ply\nformat nonsense\n\x00\x01")
    with pytest.raises(ModelError):
        load_mesh(garbage)


def test_winding_repair_agrees_with_trimesh_and_is_consistent():
    rng = np.random.default_rng(3)
    parts = [trimesh.creation.icosphere(3), trimesh.creation.box((1, 2, 3)), trimesh.creation.cylinder(0.5, 2)]
    offset, faces, verts = 0, [], []
    for m in parts:
        verts.append(np.asarray(m.vertices) + 5.0 * offset)
        faces.append(np.asarray(m.faces) + sum(len(v) for v in verts[:-1]))
        offset += 1
    v, f = np.vstack(verts), np.vstack(faces)
    flip = rng.random(len(f)) < 0.3
    flip[[0, len(parts[0].faces), len(parts[0].faces) + len(parts[1].faces)]] = False  # each part's first face
    f[flip] = f[flip][:, ::-1]
    mine = oriented_faces(f)
    assert trimesh.Trimesh(v, mine, process=False).is_winding_consistent
    reference = trimesh.Trimesh(v, f, process=False)
    trimesh.repair.fix_winding(reference)
    assert np.array_equal(mine, np.asarray(reference.faces))


def test_the_winding_check_is_trimeshs():
    """winding_consistent decides as trimesh's is_winding_consistent, on closed shells with
    faces flipped and on random faces (open, non-manifold and degenerate edges)."""
    rng = np.random.default_rng(11)
    cases = []
    for shell in (trimesh.creation.icosphere(2), trimesh.creation.box(), trimesh.creation.cylinder(0.5, 2)):
        for share in (0.0, 0.02, 0.3):
            f = np.asarray(shell.faces).copy()
            flip = rng.random(len(f)) < share
            f[flip] = f[flip][:, ::-1]
            cases.append((np.asarray(shell.vertices), f))
    for _ in range(400):
        n = int(rng.integers(3, 10))
        cases.append((rng.normal(size=(n, 3)), rng.integers(0, n, (int(rng.integers(1, 16)), 3))))
    decided = [winding_consistent(f) for _, f in cases]
    assert decided == [trimesh.Trimesh(v, f, process=False).is_winding_consistent for v, f in cases]
    assert any(decided) and not all(decided)
    assert not winding_consistent(np.zeros((0, 3), np.int64))
