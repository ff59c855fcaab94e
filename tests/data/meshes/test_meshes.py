"""The user's textured meshes: loading (textures anywhere), object frames, manifests, folder layouts.

Every mesh is built here with trimesh (boxes and cylinders with a generated PNG texture, written as
OBJ + MTL, or PLY with vertex colours); nothing is downloaded.
"""

from __future__ import annotations

import json
import logging
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh
from PIL import Image, ImageDraw
from trimesh.visual.texture import TextureVisuals

from matl.data.meshes import (
    APCSource,
    ARCSource,
    Manifest,
    ManifestError,
    MeshError,
    MeshFolderSource,
    YCBSource,
    load_mesh_parts,
)
from matl.data.meshes.frames import guess_layout, object_frame
from matl.utils.errors import MatlError

SIZE = 32
ROOT = Path(__file__).resolve().parents[3]


def atlas(seed: int, cells: int = 6) -> Image.Image:
    """A 3 x 2 texture atlas of distinct cells: colour, stripes and a letter each (an up direction)."""
    rng = np.random.default_rng(seed)
    im = Image.new("RGB", (192, 128), (40, 40, 40))
    draw = ImageDraw.Draw(im)
    for k in range(cells):
        x, y = (k % 3) * 64, (k // 3) * 64
        colour = tuple(int(c) for c in rng.integers(60, 255, 3))
        draw.rectangle((x, y, x + 63, y + 63), fill=colour)
        draw.rectangle((x + 4, y + 4, x + 30, y + 20), fill=(250, 250, 250))
        draw.text((x + 36, y + 30), "ABCDEF"[k], fill=(20, 20, 20))
    return im


def textured_box(extents: tuple[float, float, float], seed: int) -> trimesh.Trimesh:
    """A box whose 6 faces each map to one atlas cell."""
    box = trimesh.creation.box(extents=extents)
    box.unmerge_vertices()
    uv = np.zeros((len(box.vertices), 2))
    normals = box.face_normals
    for f, (face, n) in enumerate(zip(box.faces, normals, strict=True)):
        axis = int(np.argmax(np.abs(n)))
        cell = 2 * axis + int(n[axis] > 0)
        u_axis, v_axis = [i for i in range(3) if i != axis]
        p = box.vertices[face]
        u = (p[:, u_axis] / extents[u_axis] + 0.5) * 0.9 + 0.05
        v = (p[:, v_axis] / extents[v_axis] + 0.5) * 0.9 + 0.05
        uv[face] = np.column_stack([((cell % 3) + u) / 3, 1 - ((cell // 3) + (1 - v)) / 2])
        del f
    box.visual = TextureVisuals(uv=uv, image=atlas(seed))
    return box


def textured_cylinder(radius: float, height: float, seed: int) -> trimesh.Trimesh:
    cyl = trimesh.creation.cylinder(radius=radius, height=height, sections=48)
    cyl.unmerge_vertices()
    v = cyl.vertices
    angle = (np.arctan2(v[:, 1], v[:, 0]) / (2 * math.pi)) % 1.0
    uv = np.column_stack([angle, (v[:, 2] / height + 0.5) * 0.5])
    cyl.visual = TextureVisuals(uv=uv, image=atlas(seed))
    return cyl


def write_obj(mesh: trimesh.Trimesh, path: Path, texture_dir: Path | None = None) -> Path:
    """Export ``mesh`` as OBJ + MTL + PNG into ``path``'s folder; with ``texture_dir`` the PNG is
    moved there and the MTL points at it with a relative path outside the mesh folder."""
    path.parent.mkdir(parents=True, exist_ok=True)
    mesh.export(path, include_texture=True, mtl_name=f"{path.stem}.mtl")
    mtl = path.with_suffix(".mtl")
    png = next(path.parent.glob("*.png"))
    if texture_dir is not None:
        texture_dir.mkdir(parents=True, exist_ok=True)
        target = texture_dir / f"{path.parent.name}_{png.name}"
        os.replace(png, target)
        rel = os.path.relpath(target, path.parent)
        mtl.write_text(mtl.read_text().replace(f"map_Kd {png.name}", f"map_Kd -s 1 1 1 {rel}"))
    return path


def coloured_ply(path: Path, extents: tuple[float, float, float], seed: int) -> Path:
    box = trimesh.creation.box(extents=extents).subdivide().subdivide()
    rng = np.random.default_rng(seed)
    box.visual.vertex_colors = np.column_stack([rng.integers(40, 255, (len(box.vertices), 3)),
                                                np.full(len(box.vertices), 255)]).astype(np.uint8)  # fmt: skip
    path.parent.mkdir(parents=True, exist_ok=True)
    box.export(path)
    return path


# ------------------------------------------------------------------------------------------ loading


def test_texture_outside_the_mesh_folder_is_loaded(tmp_path: Path) -> None:
    obj = write_obj(textured_box((4, 2, 6), 0), tmp_path / "objects" / "box" / "box.obj", tmp_path / "shared_tex")
    assert not list(obj.parent.glob("*.png"))
    assert "../../shared_tex/" in obj.with_suffix(".mtl").read_text()
    parts = load_mesh_parts(obj)
    assert len(parts) == 1 and parts[0].visual.material.image.size == (192, 128)


def test_missing_texture_names_the_file(tmp_path: Path) -> None:
    obj = write_obj(textured_box((4, 2, 6), 0), tmp_path / "box" / "box.obj", tmp_path / "tex")
    texture = next((tmp_path / "tex").glob("*.png"))
    texture.unlink()
    with pytest.raises(MeshError) as e:
        load_mesh_parts(obj)
    message = str(e.value)
    assert "\n" not in message and str(obj) in message and texture.name in message and "not found" in message
    assert isinstance(e.value, MatlError)


def test_untextured_corrupt_and_missing_meshes(tmp_path: Path) -> None:
    plain = tmp_path / "plain.obj"
    trimesh.creation.box().export(plain)
    with pytest.raises(MeshError, match="has no texture"):
        load_mesh_parts(plain)
    assert load_mesh_parts(plain, require_texture=False)
    bad = tmp_path / "bad.obj"
    bad.write_text("this is not\nv 1 2\nf 1 2 9\n")
    with pytest.raises(MeshError, match=r"bad\.obj: "):
        load_mesh_parts(bad)
    with pytest.raises(MeshError, match="no such mesh file"):
        load_mesh_parts(tmp_path / "nothing.obj")
    notimage = write_obj(textured_box((1, 1, 1), 1), tmp_path / "ni" / "ni.obj")
    next(notimage.parent.glob("*.png")).write_bytes(b"not a png")
    with pytest.raises(MeshError, match="cannot be read: not an image"):
        load_mesh_parts(notimage)


def test_vertex_coloured_ply(tmp_path: Path) -> None:
    parts = load_mesh_parts(coloured_ply(tmp_path / "c.ply", (2, 3, 4), 0))
    assert parts[0].visual.kind == "vertex"


def test_ply_texture_file_outside_folder(tmp_path: Path) -> None:
    box = textured_box((2, 2, 2), 3)
    (tmp_path / "tex").mkdir()
    box.visual.material.image.save(tmp_path / "tex" / "t.png")
    ply = tmp_path / "mesh" / "m.ply"
    ply.parent.mkdir()
    data = trimesh.exchange.ply.export_ply(box, encoding="ascii")
    ply.write_bytes(data.replace(b"end_header", b"comment TextureFile ../tex/t.png\nend_header", 1))
    assert load_mesh_parts(ply)[0].visual.material.image.size == (192, 128)
    (tmp_path / "tex" / "t.png").unlink()
    with pytest.raises(MeshError, match=r"t\.png \(TextureFile in its header\) not found"):
        load_mesh_parts(ply)


# ------------------------------------------------------------------------------------------ frames


def _rot_z(deg: float) -> np.ndarray:
    return trimesh.transformations.rotation_matrix(math.radians(deg), [0, 0, 1])


def test_object_frame_of_a_turned_box() -> None:
    box = trimesh.creation.box(extents=(4, 2, 6))
    box.apply_transform(_rot_z(30))
    box.apply_translation([5, -3, 1])
    frame = object_frame(box.vertices, "rectangular")
    assert np.allclose(frame.extents, [4, 2, 6], atol=1e-6)
    assert np.allclose(frame.centre, [5, -3, 1], atol=1e-6)
    assert np.allclose(frame.rotation[2], [0, 0, 1], atol=1e-6)  # up stays up
    assert frame.rotation[1] @ [0, -1, 0] < 0  # the front (-y) faces the mesh's -y
    assert np.isclose(np.linalg.det(frame.rotation), 1.0)
    moved = trimesh.transform_points(box.vertices, frame.transform)
    assert np.allclose(np.ptp(moved, axis=0), [4, 2, 6], atol=1e-6) and np.allclose(moved.mean(0), 0, atol=1e-6)


def test_cylinder_axis_is_the_most_distinct_one() -> None:
    lying = trimesh.creation.cylinder(radius=1.0, height=5.0, sections=64)
    lying.apply_transform(trimesh.transformations.rotation_matrix(math.pi / 2, [0, 1, 0]))  # axis along x
    frame = object_frame(lying.vertices, "cylindrical")
    assert abs(frame.rotation[2] @ [1, 0, 0]) > 0.999
    assert np.allclose(frame.extents, [2, 2, 5], atol=0.01)  # a 64-gon is a little narrower than its circle
    squat = trimesh.creation.cylinder(radius=3.0, height=1.0, sections=64)  # a tuna tin: axis is the short one
    assert abs(object_frame(squat.vertices, "cylindrical").rotation[2] @ [0, 0, 1]) > 0.999


def test_planar_frame_standing_and_lying() -> None:
    card = trimesh.creation.box(extents=(10, 0.3, 15))
    frame = object_frame(card.vertices, "planar")
    assert np.allclose(np.abs(frame.rotation[1]), [0, 1, 0]) and np.allclose(frame.rotation[2], [0, 0, 1])
    flat = trimesh.creation.box(extents=(10, 15, 0.3))  # lying on the table: the front is the top face
    frame = object_frame(flat.vertices, "planar")
    assert np.allclose(-frame.rotation[1], [0, 0, 1]) and np.allclose(frame.rotation[2], [0, 1, 0])


def test_guess_layout_from_proportions() -> None:
    assert guess_layout(trimesh.creation.box(extents=(10, 0.5, 14)).vertices) == "planar"
    assert guess_layout(trimesh.creation.cylinder(radius=2, height=6, sections=48).vertices) == "cylindrical"
    assert guess_layout(trimesh.creation.box(extents=(3, 3.2, 6)).vertices) == "rectangular"


# ------------------------------------------------------------------------------------------ manifests


def test_manifest_yaml_and_csv(tmp_path: Path) -> None:
    (tmp_path / "m.yaml").write_text(
        "defaults: {up: +y}\nobjects:\n  003_cracker_box: rectangular\n"
        "  Mug: {shape: nonplanar, planes: cylindrical, yaw_deg: 45}\n"
    )
    m = Manifest.load(tmp_path / "m.yaml")
    assert m.lookup("cracker_box").shape == "rectangular" and m.lookup("003_CRACKER_BOX").layout == "rectangular"
    assert m.lookup("mug").layout == "cylindrical" and m.lookup("mug").yaw_deg == 45 and m.defaults["up"] == "+y"
    assert m.lookup("other") is None
    (tmp_path / "m.csv").write_text("object,shape,planes,up\nbox_a,rectangular,,\nbag,nonplanar,rectangular,+y\n")
    c = Manifest.load(tmp_path / "m.csv")
    assert c.lookup("bag").planes == "rectangular" and c.lookup("bag").up == "+y" and c.lookup("box_a").up is None
    (tmp_path / "bad.yaml").write_text("objects:\n  thing: sphere\n")
    with pytest.raises(ManifestError, match=r"bad\.yaml: thing: shape 'sphere' is invalid"):
        Manifest.load(tmp_path / "bad.yaml")
    (tmp_path / "bad2.yaml").write_text("objects:\n  thing: {shape: planar, planes: cylindrical}\n")
    with pytest.raises(ManifestError, match="contradicts"):
        Manifest.load(tmp_path / "bad2.yaml")
    assert len(Manifest.load("ycb").entries) > 50  # the shipped manifests parse


# ------------------------------------------------------------------------------------------ layouts


@pytest.fixture
def ycb_root(tmp_path: Path) -> Path:
    root = tmp_path / "ycb"
    write_obj(textured_box((16, 6, 21), 0), root / "003_cracker_box" / "google_16k" / "textured.obj")
    write_obj(textured_cylinder(3.3, 10, 1), root / "005_tomato_soup_can" / "google_16k" / "textured.obj",
              tmp_path / "elsewhere")  # fmt: skip
    write_obj(textured_box((12, 18, 0.8), 2), root / "900_test_card" / "google_16k" / "textured.obj")
    write_obj(textured_box((7, 5, 17), 3), root / "006_mustard_bottle" / "google_16k" / "textured.obj")
    (root / "099_no_scan" / "poisson").mkdir(parents=True)
    return root


def test_ycb_layout_manifest_and_guess(ycb_root: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.INFO):
        source = YCBSource(ycb_root, manifest="ycb")
        names = [n for n, _, _ in source.objects()]
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warned) == 1 and "not in the manifest" in warned[0] and "900_test_card" in warned[0]
    assert names == ["003_cracker_box", "005_tomato_soup_can", "006_mustard_bottle", "900_test_card"]
    assert any("099_no_scan" in r.getMessage() and "google_16k" in r.getMessage() for r in caplog.records)
    cs = source.build(SIZE)
    assert cs.object_shapes == ["rectangular", "cylindrical", "nonplanar", "planar"]  # last one guessed
    per_object = np.bincount(cs.plane_object).tolist()
    assert per_object == [6, 10, 6, 2]
    assert cs.plane_names[6:8] == ["top", "bottom"] and cs.plane_names[-2:] == ["front", "back"]
    assert not cs.images[~cs.masks].any() and cs.masks.reshape(cs.num_planes, -1).any(1).all()
    for p in range(cs.num_planes):  # catalog framing: larger extent covers 0.6, centred
        ys, xs = np.nonzero(cs.masks[p])
        assert abs(max(np.ptp(xs), np.ptp(ys)) + 1 - 0.6 * SIZE) <= 2.0, cs.plane_label(p)
        assert np.allclose(((xs.min() + xs.max()) / 2, (ys.min() + ys.max()) / 2), (SIZE - 1) / 2, atol=1.0)
    # the cracker box's 6 faces show different atlas cells
    faces = cs.images[:6].reshape(6, -1).astype(float)
    assert min(np.abs(faces[i] - faces[j]).mean() for i in range(6) for j in range(i)) > 1.0
    subset = YCBSource(ycb_root, manifest="ycb", subset="nonplanar", only_manifest=True)
    assert [n for n, _, _ in subset.objects()] == ["006_mustard_bottle"]


def test_mesh_source_renders_views_too(ycb_root: Path, tmp_path: Path) -> None:
    from matl.data.view_pool import load_view_pool
    from matl.data.view_sampler import ViewSampler

    source = YCBSource(ycb_root, manifest="ycb", only_manifest=True, subset="planar")
    pool = load_view_pool(source, SIZE, 2, ViewSampler(), 0, tmp_path / "cache")
    assert pool.images.shape == (16, 2, SIZE, SIZE, 3) and pool.object_names == ["003_cracker_box",
                                                                                  "005_tomato_soup_can"]
    assert pool.images.reshape(32, -1).max(1).min() > 0


def test_apc_arc_and_meshes_layouts(tmp_path: Path) -> None:
    apc = tmp_path / "apc"
    mesh = APCSource.MESH
    write_obj(textured_box((20, 6, 28), 4), (apc / "cheezit_big_original" / mesh).with_name(mesh.name),
              apc / "cheezit_big_original" / "textures")  # fmt: skip
    write_obj(textured_cylinder(5, 12, 5), apc / "rolodex_jumbo_pencil_cup" / mesh)
    (apc / "empty_object").mkdir()
    source = APCSource(apc, manifest="apc")
    assert [n for n, _, _ in source.objects()] == ["cheezit_big_original", "rolodex_jumbo_pencil_cup"]
    assert source.build(SIZE).num_planes == 16

    arc = tmp_path / "arc"
    write_obj(textured_box((8, 3, 20), 6), arc / "Reynolds_Wrap" / "reynolds_wrap.obj")
    coloured_ply(arc / "Tissue_Box" / "model.ply", (23, 12, 9), 7)
    cs = ARCSource(arc, manifest="arc").build(SIZE)
    assert cs.object_names == ["Reynolds_Wrap", "Tissue_Box"] and cs.object_shapes == ["rectangular"] * 2

    folder = tmp_path / "mine"
    write_obj(textured_box((5, 5, 9), 8), folder / "cube_thing.obj")
    write_obj(textured_cylinder(2, 9, 9), folder / "nested" / "deep" / "can.obj")
    rows = ["object,shape,mesh", "cube_thing,rectangular,", "can,cylindrical,nested/deep/can.obj"]
    (folder / "manifest.csv").write_text("\n".join(rows) + "\n")
    cs = MeshFolderSource(folder, manifest=folder / "manifest.csv").build(SIZE)
    assert cs.object_names == ["can", "cube_thing"] and cs.object_shapes == ["cylindrical", "rectangular"]
    (folder / "manifest.csv").write_text("object,shape,mesh\ncan,cylindrical,nested/missing.obj\n")
    with pytest.raises(MeshError, match=r"missing\.obj: no such mesh file"):
        MeshFolderSource(folder, manifest=folder / "manifest.csv").objects()


def test_cache_key_follows_the_files(ycb_root: Path) -> None:
    kw = {"manifest": "ycb", "only_manifest": True}
    before = YCBSource(ycb_root, **kw).cache_key()
    assert YCBSource(ycb_root, **kw).cache_key() == before
    png = next((ycb_root / "003_cracker_box" / "google_16k").glob("*.png"))
    os.utime(png, ns=(png.stat().st_atime_ns, png.stat().st_mtime_ns + 10**9))
    assert YCBSource(ycb_root, **kw).cache_key() != before


def test_root_problems_are_one_line_errors(tmp_path: Path) -> None:
    with pytest.raises(MatlError, match="no such folder"):
        YCBSource(tmp_path / "nope")
    with pytest.raises(MatlError, match="no ycb meshes found"):
        YCBSource(tmp_path).objects()


def _render(args: list[str], tmp_path: Path) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "matl.render", *args, f"paths.cache_dir={tmp_path / 'cache'}",
           f"hydra.run.dir={tmp_path / 'run'}", "data.image_size=24"]  # fmt: skip
    env = {**os.environ, "PYOPENGL_PLATFORM": os.environ.get("PYOPENGL_PLATFORM", "egl")}
    return subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)


def test_render_cli_reports_mesh_problems_in_one_line(ycb_root: Path, tmp_path: Path) -> None:
    broken = ycb_root / "006_mustard_bottle" / "google_16k" / "textured.obj"
    broken.write_text("v 0 0 0\nf 1 2 3\nthis is garbage\n")
    out = _render(["data=ycb", f"data.source.root={ycb_root}"], tmp_path)
    assert out.returncode == 2, out.stderr[-2000:]
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and str(broken) in lines[0], out.stderr[-2000:]
    assert "Traceback" not in out.stderr
    unset = _render(["data=ycb"], tmp_path)
    assert unset.returncode == 2 and unset.stderr.strip() == (
        "error: data.source.root is not set: pass data.source.root=<path> (see docs/datasets.md)"
    ), unset.stderr[-2000:]


def test_render_cli_previews_views_and_measures_speed(tmp_path: Path) -> None:
    """``python -m matl.render data=meshes ... views=1 speed=true``: gallery.png, views.png and speed.json."""
    folder = tmp_path / "mine"
    write_obj(textured_box((5, 5, 9), 8), folder / "cube_thing.obj")
    (folder / "manifest.csv").write_text("object,shape\ncube_thing,rectangular\n")
    out = _render(["data=meshes", f"data.source.root={folder}", f"data.source.manifest={folder / 'manifest.csv'}",
                   "views=1", "speed=true", "speed_objects=1", "speed_views=2"], tmp_path)  # fmt: skip
    assert out.returncode == 0, out.stderr[-2000:]
    run = tmp_path / "run"
    assert (run / "gallery.png").is_file() and (run / "views.png").is_file()
    speed = json.loads((run / "speed.json").read_text())
    assert speed["image_size"] == 24 and speed["canonical"]["images"] == 6 and speed["views"]["images"] == 12
    assert speed["canonical"]["images_per_s"] > 0
