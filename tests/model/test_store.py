"""The prepared-model store: what it reads back equals what preparation makes, and an entry that
is stale, corrupt or unreadable is rebuilt, never trusted."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest
import trimesh

from vehicle_pose import RegistrationOptions, register
from vehicle_pose.model.library import ModelLibrary, model_from_mesh
from vehicle_pose.model.loading import load_mesh
from vehicle_pose.model.mesh import Mesh
from vehicle_pose.model.store import ModelStore, default_budgets, default_cache_dir
from vehicle_pose.render.synth import synthesize

from helpers import view

SEDAN = ModelLibrary().info("sedan").mesh_path


def _same(a: Mesh, b: Mesh) -> None:
    assert len(a.parts) == len(b.parts)
    for p, q in zip(a.parts, b.parts, strict=True):
        assert (p.name, p.kind, p.one_sided) == (q.name, q.kind, q.one_sided)
        for field in ("vertices", "normals", "faces", "albedo", "uv", "texture"):
            x, y = getattr(p, field), getattr(q, field)
            assert (x is None) == (y is None), field
            if x is not None:
                assert x.dtype == y.dtype and np.array_equal(x, y), field


def _entry(store: ModelStore) -> Path:
    (folder,) = [p for p in store.root.iterdir() if p.is_dir()]
    return folder


def _write_obj(folder: Path, colour: str = "0.8 0.2 0.2") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    box = trimesh.creation.box((4.0, 1.8, 1.4))
    lines = ["mtllib car.mtl", "usemtl paint"] + [f"v {x} {y} {z}" for x, y, z in box.vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in box.faces]
    (folder / "car.obj").write_text("\n".join(lines) + "\n")
    (folder / "car.mtl").write_text(f"newmtl paint\nKd {colour}\n")
    return folder / "car.obj"


def test_prepared_model_reads_back_the_same_arrays_levels_and_exteriors(tmp_path, renderer):
    store = ModelStore(tmp_path / "store")
    first = model_from_mesh(SEDAN, store=store)
    first.prepare(renderer)
    budgets = default_budgets(first.mesh.n_faces)
    assert budgets[0] == 4096 and budgets[-1] >= first.mesh.n_faces

    again = model_from_mesh(SEDAN, store=store)
    assert again.levels is not None and again.levels.missing(budgets, renderer) == []
    _same(first.mesh, again.mesh)
    for b in budgets:
        _same(first.lod(b), again.lod(b))
        _same(first.exterior(b, renderer), again.exterior(b, renderer))
    assert again.info.wheels is not None
    assert again.info.wheels.to_dict() == first.info.wheels.to_dict()
    # Read back, not recomputed: no level of the second model was decimated or passed again.
    assert again.lod(4096) is again.levels.lod(4096, make=lambda b: pytest.fail("decimated again"))


def test_reading_a_prepared_model_imports_no_mesh_library(tmp_path, renderer):
    """A prepared model is arrays: reading one needs neither trimesh, the simplifier nor numba
    (numba's import alone took longer than the read)."""
    import subprocess
    import sys

    obj = _write_obj(tmp_path / "mesh")  # with a material library naming a texture not there,
    (obj.parent / "car.mtl").write_text("newmtl paint\nKd 0.8 0.2 0.2\nmap_Kd gone.png\n")  # checked on reading
    model_from_mesh(obj, store=ModelStore(tmp_path / "store")).prepare(renderer)
    code = ("import sys\nfrom vehicle_pose.model.library import model_from_mesh\n"
            "from vehicle_pose.model.store import ModelStore\n"
            "m = model_from_mesh(sys.argv[1], store=ModelStore(sys.argv[2]))\n"
            "assert m.mesh.n_faces == 12\n"
            "heavy = [n for n in ('trimesh', 'fast_simplification', 'numba') if n in sys.modules]\n"
            "assert not heavy, heavy\n")
    done = subprocess.run([sys.executable, "-c", code, str(obj), str(tmp_path / "store")], capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stderr


def test_registration_is_identical_with_and_without_the_store(tmp_path, renderer):
    store = ModelStore(tmp_path / "store")
    plain = model_from_mesh(SEDAN)
    stored = model_from_mesh(SEDAN, store=store)
    stored.prepare(renderer)
    stored = model_from_mesh(SEDAN, store=store)  # every level now read from disk
    truth = view(plain, 35.0, 12.0, width=320, height=240, focal=450.0)
    rgb, _ = synthesize(plain.mesh, truth, renderer=renderer, seed=4)
    start = view(plain, 41.0, 9.0, width=320, height=240, focal=450.0)
    options = RegistrationOptions.from_flat(max_evaluations=120, grabcut=False, edge_weight=0.0, focal_starts=())
    a = register(rgb, plain, init_camera=start, options=options, renderer=renderer)
    b = register(rgb, stored, init_camera=start, options=options, renderer=renderer)
    for x, y in ((a.camera.K, b.camera.K), (a.camera.R, b.camera.R), (a.camera.t, b.camera.t)):
        assert np.abs(x - y).max() <= 1e-9 * max(1.0, np.abs(x).max())
    assert a.loss == b.loss and a.evaluations == b.evaluations


def test_corrupt_array_or_manifest_is_rebuilt(tmp_path, caplog):
    store = ModelStore(tmp_path / "store")
    reference = model_from_mesh(SEDAN)
    model_from_mesh(SEDAN, store=store)
    folder = _entry(store)
    victim = max((folder / "arrays").iterdir(), key=lambda p: p.stat().st_size)
    data = bytearray(victim.read_bytes())
    data[-9] ^= 0xFF
    victim.write_bytes(bytes(data))
    with caplog.at_level(logging.WARNING, logger="vehicle_pose.model.store"):
        again = model_from_mesh(SEDAN, store=store)
    assert "unreadable" in caplog.text
    _same(reference.mesh, again.mesh)
    (folder / "manifest.json").write_text("{not json")
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="vehicle_pose.model.store"):
        third = model_from_mesh(SEDAN, store=store)
    assert "unreadable" in caplog.text
    _same(reference.mesh, third.mesh)
    assert json.loads((folder / "manifest.json").read_text())["lods"]["full"]


def test_a_changed_material_file_makes_the_entry_stale(tmp_path):
    store = ModelStore(tmp_path / "store")
    path = _write_obj(tmp_path / "car", "0.8 0.8 0.8")
    bright = model_from_mesh(path, store=store).mesh.parts[0].albedo[0]
    assert model_from_mesh(path, store=store).mesh.parts[0].albedo[0] == bright
    (tmp_path / "car" / "car.mtl").write_text("newmtl paint\nKd 0.1 0.1 0.1\n")
    dark = model_from_mesh(path, store=store).mesh.parts[0].albedo[0]
    assert dark < 0.5 * bright
    assert dark == load_mesh(path).parts[0].albedo[0]


def test_a_changed_mesh_file_gets_its_own_entry(tmp_path):
    store = ModelStore(tmp_path / "store")
    path = _write_obj(tmp_path / "car")
    k1 = store.key(path, [])
    path.write_text(path.read_text().replace("v 2.0", "v 2.5", 1))
    assert store.key(path, []) != k1
    model_from_mesh(path, store=store)
    assert (store.root / store.key(path, [])).is_dir()


def test_unwritable_store_still_loads(tmp_path):
    blocked = tmp_path / "file"
    blocked.write_text("not a folder")
    model = model_from_mesh(SEDAN, store=ModelStore(blocked / "store"))
    _same(model.mesh, load_mesh(SEDAN))


def test_cache_dir_follows_the_xdg_convention(monkeypatch, tmp_path):
    monkeypatch.delenv("VEHICLE_POSE_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert default_cache_dir() == tmp_path / "xdg" / "vehicle-pose"
    monkeypatch.setenv("XDG_CACHE_HOME", "relative/ignored")
    assert default_cache_dir() == Path.home() / ".cache" / "vehicle-pose"
    monkeypatch.setenv("VEHICLE_POSE_CACHE_DIR", str(tmp_path / "mine"))
    assert default_cache_dir() == tmp_path / "mine"
