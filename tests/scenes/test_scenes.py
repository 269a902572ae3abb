"""hlbvh.scenes: procedural animated scenes, apply_frame, and per-frame mesh sequences.

References: Mitsuba's own loader and renderer (ids after mi.load_dict, buffers through
mi.traverse, native renders), closed-form volumes, rigid-motion invariants (distances
inside a rigid piece), and PLY files written by Mitsuba (mi.Mesh.write_ply).
"""

from __future__ import annotations

import shutil

import hlbvh  # noqa: F401  (sets up Dr.Jit's LLVM and the Mitsuba variant)
import mitsuba as mi
import numpy as np
import pytest

from hlbvh import scenes
from hlbvh.scenes import meshes as scene_meshes
from hlbvh.scenes import rigid as rigid_module
from hlbvh.scenes.procedural import mesh_object

SMALL = 3000  # triangles: every scene at this size loads and renders in well under a second
NAMES = ["cloth", "twist", "fracture", "rigid", "soup", "world"]
TINY_RENDER = dict(resolution=(40, 24), spp=2)


def buffer(params, key) -> np.ndarray:
    return np.array(params[key])


def loaded(name, **kwargs):
    animation = scenes.get(name, triangles=SMALL, frames=12, **kwargs)
    scene = mi.load_dict(animation.scene_dict(**TINY_RENDER))
    return animation, scene, mi.traverse(scene)


# ---- The catalogue -------------------------------------------------------------------


def test01_names_and_bad_arguments():
    assert scenes.names() == NAMES + ["flock", "fog"]  # tested in test_flock, test_volpath
    with pytest.raises(ValueError, match="unknown"):
        scenes.get("teapot")
    with pytest.raises(ValueError, match="colour"):
        scenes.get("cloth", colour="red")
    for bad in (0, -5, 2.5, True, "many"):
        with pytest.raises(ValueError, match="triangles"):
            scenes.get("twist", triangles=bad)
    with pytest.raises(ValueError, match="frames"):
        scenes.get("soup", frames=0)
    with pytest.raises(ValueError, match="pieces"):
        scenes.get("fracture", pieces=1)
    with pytest.raises(ValueError, match="groups"):
        scenes.get("rigid", objects=4, groups=5)
    with pytest.raises(ValueError, match="resolution"):
        scenes.get("cloth", triangles=SMALL).scene_dict(resolution=(0, 10))


@pytest.mark.parametrize("name", NAMES)
def test02_loaded_shapes_keep_their_ids_and_counts(name):
    """Every part survives mi.load_dict (default optimize=True, and optimize=False) as its
    own shape under its id, with the triangle count the scene reports."""
    animation = scenes.get(name, triangles=SMALL, frames=12)
    counts = animation.triangle_counts()
    ids = animation.animated_ids() + animation.static_ids()
    assert sorted(ids) == sorted(counts) and len(set(ids)) == len(ids)
    assert animation.animated_ids() and animation.static_ids()
    for optimize in (True, False):
        scene = mi.load_dict(animation.scene_dict(**TINY_RENDER), optimize=optimize)
        shapes = {shape.id(): shape for shape in scene.shapes()}
        assert sorted(shapes) == sorted(ids)
        assert {sid: shapes[sid].face_count() for sid in ids} == counts
        params = mi.traverse(scene)
        for sid in ids:
            assert f"{sid}.vertex_positions" in params and f"{sid}.faces" in params
    film = scene.sensors()[0].film()
    assert list(film.size()) == [40, 24]
    assert "BoxFilter" in str(film.rfilter())
    assert scene.sensors()[0].sampler().sample_count() == 2
    assert animation.triangle_count() >= SMALL


@pytest.mark.parametrize("name", NAMES)
def test03_triangle_knob_reaches_two_million_without_building(name):
    previous = 0
    for request in (20_000, 200_000, 2_000_000):
        animation = scenes.get(name, triangles=request)
        total = animation.triangle_count()
        assert request <= total <= 1.15 * request, (request, total)
        assert total > previous
        previous = total
        assert "parts" not in vars(animation), "counting built the geometry"


# ---- Frames --------------------------------------------------------------------------


@pytest.mark.parametrize("name", NAMES)
def test04_frames_are_finite_sized_and_move_only_animated_shapes(name):
    animation, scene, params = loaded(name)
    static_before = {sid: buffer(params, f"{sid}.vertex_positions") for sid in animation.static_ids()}
    first = animation.frame(0)
    assert list(first) == animation.animated_ids()
    for sid, geometry in first.items():
        loaded_positions = buffer(params, f"{sid}.vertex_positions")
        assert geometry.positions.dtype == np.float32
        assert geometry.positions.shape == loaded_positions.shape
        assert geometry.faces is None
        # The dict holds frame 0.
        assert np.array_equal(geometry.positions, loaded_positions)
    last = animation.frame_count - 1
    for i in (1, last):
        frame = animation.frame(i)
        changed = scenes.apply_frame(scene, params, frame)
        assert changed == animation.animated_ids()
        for sid, geometry in frame.items():
            assert np.isfinite(geometry.positions).all()
            assert geometry.positions.size == 3 * scene_shape(scene, sid).vertex_count()
            assert np.array_equal(buffer(params, f"{sid}.vertex_positions"), geometry.positions)
    for sid in animation.animated_ids():
        assert not np.array_equal(animation.frame(last)[sid].positions, first[sid].positions), sid
    for sid, before in static_before.items():
        assert np.array_equal(buffer(params, f"{sid}.vertex_positions"), before), sid
    with pytest.raises(ValueError, match="frame"):
        animation.frame(animation.frame_count)
    with pytest.raises(ValueError, match="frame"):
        animation.frame(-1)


def scene_shape(scene, sid):
    return next(shape for shape in scene.shapes() if shape.id() == sid)


@pytest.mark.parametrize("name", NAMES)
def test05_frames_are_deterministic_and_seeded(name):
    a = scenes.get(name, triangles=SMALL, frames=12)
    b = scenes.get(name, triangles=SMALL, frames=12)
    c = scenes.get(name, triangles=SMALL, frames=12, seed=7)
    i = 9
    fa, fb, fc = a.frame(i), b.frame(i), c.frame(i)
    fa_again = a.frame(i)  # random access: no state carried between calls
    for sid in fa:
        assert np.array_equal(fa[sid].positions, fb[sid].positions)
        assert np.array_equal(fa[sid].positions, fa_again[sid].positions)
    assert any(
        fa[sid].positions.shape != fc[sid].positions.shape
        or not np.array_equal(fa[sid].positions, fc[sid].positions)
        for sid in fa
    )


def test06_apply_frame_changes_the_native_render():
    animation, scene, params = loaded("cloth")
    before = np.array(mi.render(scene, params, seed=3))
    scenes.apply_frame(scene, params, animation.frame(6))
    after = np.array(mi.render(scene, params, seed=3))
    assert np.isfinite(after).all()
    assert np.abs(after - before).max() > 0.05
    # The same frame, again or in another scene loaded from the same animation, renders
    # the same image to the bit (vertex normals are computed deterministically).
    scenes.apply_frame(scene, params, animation.frame(6))
    assert np.array_equal(np.array(mi.render(scene, params, seed=3)), after)
    other = mi.load_dict(animation.scene_dict(**TINY_RENDER))
    other_params = mi.traverse(other)
    scenes.apply_frame(other, other_params, animation.frame(6))
    assert np.array_equal(np.array(mi.render(other, other_params, seed=3)), after)
    assert np.array_equal(buffer(other_params, "flag.vertex_normals"), buffer(params, "flag.vertex_normals"))


def test07_apply_frame_accepts_new_topology_and_rejects_bad_geometry():
    animation, scene, params = loaded("twist")
    bar = animation.frame(2)["bar"].positions.reshape(-1, 3)
    # A new topology: the first 10 triangles only, with their own vertices.
    faces = animation.parts["bar"].faces[:10]
    positions = bar[faces.reshape(-1)]
    new_faces = np.arange(30, dtype=np.uint32)
    geometry = scenes.FrameGeometry(positions.reshape(-1), new_faces)
    assert (geometry.vertex_count, geometry.face_count) == (30, 10)
    assert scenes.apply_frame(scene, params, {"bar": geometry}) == ["bar"]
    assert scene_shape(scene, "bar").face_count() == 10
    assert np.array_equal(buffer(params, "bar.faces"), new_faces)
    # The same as Dr.Jit arrays.
    dr_geometry = scenes.FrameGeometry(mi.Float(positions.reshape(-1)), mi.UInt32(new_faces))
    scenes.apply_frame(scene, params, {"bar": dr_geometry})
    assert np.isfinite(np.array(mi.render(scene, params))).all()

    good = positions.reshape(-1)
    poisoned = good.copy()
    poisoned[4] = np.inf
    bad_cases = {
        "no mesh with that id": {"nothing": scenes.FrameGeometry(good)},
        "no faces were given": {"bar": scenes.FrameGeometry(good[:-9])},
        "non-finite": {"bar": scenes.FrameGeometry(poisoned)},
        "multiple of 3|3 per vertex": {"bar": scenes.FrameGeometry(good[:-1], new_faces)},
        "face index 30": {"bar": scenes.FrameGeometry(good, new_faces + 1)},
    }
    for message, frame in bad_cases.items():
        with pytest.raises(ValueError, match=message):
            scenes.apply_frame(scene, params, frame)
    with pytest.raises(ValueError, match="face index 99"):
        scenes.apply_frame(
            scene, params, {"bar": scenes.FrameGeometry(mi.Float(good), mi.UInt32(new_faces + 70))}
        )
    with pytest.raises(ValueError, match="non-finite"):
        scenes.apply_frame(scene, params, {"bar": scenes.FrameGeometry(mi.Float(poisoned), new_faces)})


# ---- The geometry of particular scenes ----------------------------------------------


def signed_volume(positions, faces) -> np.ndarray:
    p = positions[faces.astype(np.int64)]
    return np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])) / 6.0


def test08_mesh_builders_are_closed_and_outward():
    cases = [
        (scene_meshes.torus(1.0, 0.3, 96, 48), 2 * np.pi**2 * 1.0 * 0.3**2),
        (scene_meshes.rounded_box(24, 2.0), 4 / 3 * np.pi),
        (scene_meshes.capped_tube(96, 3), np.pi),
        (rigid_module._box((0, 0, 0), (1, 2, 3)), 6.0),
    ]
    for (positions, faces), volume in cases:
        assert signed_volume(positions, faces).sum() == pytest.approx(volume, rel=0.01)
    # Triangle counts the module docstring states.
    assert len(scene_meshes.grid(5, 3)[1]) == 30
    assert len(scene_meshes.rounded_box(5)[1]) == 12 * 25
    assert len(scene_meshes.capped_tube(7, 4)[1]) == 2 * 7 * 4 + 2 * 7
    assert len(scene_meshes.rounded_box(5)[0]) == 6 * 25 + 2


def test09_fracture_shards_are_closed_solids_that_move_rigidly():
    animation = scenes.get("fracture", triangles=40_000, frames=40)
    shards = animation._shards
    count = len(shards.centres)
    assert 200 <= count <= 1.1 * 300, "hundreds of pieces"
    # Every face lies in one piece, and each piece is a closed solid facing outward:
    # welded by position, every directed edge of a piece occurs as often as its reverse
    # (twice where a shard pinches to a line: two of its quads meet only at a corner).
    piece_of_face = shards.piece[shards.faces[:, 0].astype(np.int64)]
    assert (shards.piece[shards.faces.astype(np.int64)] == piece_of_face[:, None]).all()
    _, weld = np.unique(np.round(shards.positions, 6), axis=0, return_inverse=True)
    corners = weld.reshape(-1)[shards.faces.astype(np.int64)]
    edges = np.concatenate([corners[:, [0, 1]], corners[:, [1, 2]], corners[:, [2, 0]]])
    piece = np.tile(piece_of_face, 3)
    forward = np.stack([piece, edges[:, 0], edges[:, 1]], axis=1)
    backward = np.stack([piece, edges[:, 1], edges[:, 0]], axis=1)
    edges_f, count_f = np.unique(forward, axis=0, return_counts=True)
    edges_b, count_b = np.unique(backward, axis=0, return_counts=True)
    assert np.array_equal(edges_f, edges_b) and np.array_equal(count_f, count_b)
    assert (count_f == 1).mean() > 0.99
    volumes = np.bincount(piece_of_face, signed_volume(shards.positions, shards.faces), count)
    assert (volumes > 0).all()
    inner = 0.45 - 0.07
    shell = 2 * np.pi**2 * 1.2 * (0.45**2 - inner**2)
    assert volumes.sum() == pytest.approx(shell, rel=0.02)
    # Flying pieces keep their shape: distances between vertices of one piece.
    start, later = animation.frame(0)["shards"].positions, animation.frame(30)["shards"].positions
    start, later = start.reshape(-1, 3).astype(np.float64), later.reshape(-1, 3).astype(np.float64)
    assert np.abs(later - start).max() > 1.0
    order = np.argsort(shards.piece, kind="stable")
    same_piece = shards.piece[order][1:] == shards.piece[order][:-1]
    a, b = order[:-1][same_piece], order[1:][same_piece]
    d0 = np.linalg.norm(start[a] - start[b], axis=1)
    d1 = np.linalg.norm(later[a] - later[b], axis=1)
    assert np.abs(d1 - d0).max() < 1e-4
    assert later[:, 1].min() > -1e-3, "a shard sank into the ground"


def test10_rigid_bodies_keep_their_shape_and_stay_in_the_courtyard():
    animation = scenes.get("rigid", triangles=30_000, objects=12, groups=12)
    assert animation.animated_ids() == [f"bodies_{g}" for g in range(12)]
    scene = mi.load_dict(animation.scene_dict(**TINY_RENDER))
    assert len(scene.shapes()) == 12 + 3
    for i in (0, 17, 59):
        for sid, geometry in animation.frame(i).items():
            p = geometry.positions.reshape(-1, 3).astype(np.float64)
            q = animation.frame(0)[sid].positions.reshape(-1, 3).astype(np.float64)
            d = np.linalg.norm(p[1:] - p[:-1], axis=1)
            d0 = np.linalg.norm(q[1:] - q[:-1], axis=1)
            assert np.allclose(d, d0, atol=1e-5)
            assert p[:, 1].min() > -1e-4
            assert np.abs(p[:, [0, 2]]).max() < rigid_module.HALF_SIZE


def test11_soup_is_redrawn_every_frame():
    animation = scenes.get("soup", triangles=SMALL, frames=5)
    a, b = (animation.frame(i)["soup"].positions.reshape(-1, 3) for i in (1, 2))
    assert a.shape == b.shape == (3 * (SMALL - 2), 3)
    # Incoherent: a triangle's centroid in one frame says nothing about the next.
    ca, cb = a.reshape(-1, 3, 3).mean(axis=1), b.reshape(-1, 3, 3).mean(axis=1)
    assert abs(np.corrcoef(ca[:, 0], cb[:, 0])[0, 1]) < 0.1


# ---- Sequences from disk ---------------------------------------------------------------


FRAMES = 4


@pytest.fixture
def sequence_dir(tmp_path):
    """A scene file with a twisting bar (from PLY), a static ground and cube, and the
    bar's frames written by Mitsuba as frame_0001.ply .. frame_0004.ply."""
    twist = scenes.get("twist", triangles=1200, frames=FRAMES)
    faces = twist.parts["bar"].faces
    frames_dir = tmp_path / "frames" / "bar"
    frames_dir.mkdir(parents=True)
    written = []
    for i in range(FRAMES):
        positions = twist.frame(i)["bar"].positions.reshape(-1, 3)
        mesh_object("bar", positions, faces, {"type": "diffuse"}).write_ply(
            str(frames_dir / f"frame_{i + 1:04d}.ply")
        )
        written.append(positions.reshape(-1))
    (tmp_path / "meshes").mkdir()
    shutil.copy(frames_dir / "frame_0001.ply", tmp_path / "meshes" / "bar.ply")
    (tmp_path / "scene.xml").write_text(
        """<scene version="3.0.0">
  <bsdf type="diffuse" id="grey"/>
  <integrator type="path"><integer name="max_depth" value="4"/></integrator>
  <sensor type="perspective">
    <transform name="to_world"><lookat origin="4,2.5,6" target="0,1.5,0" up="0,1,0"/></transform>
    <film type="hdrfilm"><integer name="width" value="30"/><integer name="height" value="20"/>
      <rfilter type="gaussian"/></film>
  </sensor>
  <shape type="ply" id="bar"><string name="filename" value="meshes/bar.ply"/><ref id="grey"/></shape>
  <shape type="rectangle" id="floor"><ref id="grey"/>
    <transform name="to_world"><rotate x="1" angle="-90"/><scale value="10"/></transform></shape>
  <shape type="cube"><ref id="grey"/><transform name="to_world"><translate x="3"/></transform></shape>
  <emitter type="constant"/>
</scene>"""
    )
    return tmp_path, written, faces


def test12_sequence_round_trip_through_ply(sequence_dir):
    root, written, faces = sequence_dir
    sequence = scenes.SequenceScene(root / "scene.xml", root / "frames")
    assert sequence.frame_count == FRAMES
    assert sequence.animated_ids() == ["bar"]
    assert sorted(sequence.static_ids()) == ["floor", "shape_0"]
    assert sequence.triangle_counts()["bar"] == len(faces)
    # Shapes stay separate and addressable although they share a BSDF.
    description = sequence.scene_dict(resolution=(36, 24), spp=2)
    scene = mi.load_dict(description)
    assert sorted(s.id() for s in scene.shapes()) == ["bar", "floor", "shape_0"]
    film = scene.sensors()[0].film()
    assert list(film.size()) == [36, 24] and "BoxFilter" in str(film.rfilter())
    params = mi.traverse(scene)
    cube = buffer(params, "shape_0.vertex_positions")
    before = np.array(mi.render(scene, params, seed=1))
    for i in range(FRAMES):
        frame = sequence.frame(i)
        assert frame["bar"].faces is None
        assert np.array_equal(np.array(frame["bar"].positions), written[i])
        scenes.apply_frame(scene, params, frame)
        assert np.array_equal(buffer(params, "bar.vertex_positions"), written[i])
    assert np.array_equal(buffer(params, "shape_0.vertex_positions"), cube)
    after = np.array(mi.render(scene, params, seed=1))
    assert np.abs(after - before).max() > 0.05


def test13_sequence_scene_dict_renders_like_mitsubas_own_loader(sequence_dir):
    """The description SequenceScene hands over is the scene Mitsuba loads from the file
    (compared with a box filter: Mitsuba's wider filters splat with atomics and are not
    bit-reproducible)."""
    root, _, _ = sequence_dir
    gaussian = (root / "scene.xml").read_text()
    (root / "box.xml").write_text(gaussian.replace('<rfilter type="gaussian"/>', '<rfilter type="box"/>'))
    reference = np.array(mi.render(mi.load_file(str(root / "box.xml"), optimize=False), seed=5, spp=4))
    for source, box_filter in (("box.xml", False), ("scene.xml", True)):
        sequence = scenes.SequenceScene(root / source, root / "frames", box_filter=box_filter)
        ours = np.array(mi.render(mi.load_dict(sequence.scene_dict()), seed=5, spp=4))
        assert np.array_equal(ours, reference), source


def test14_sequence_from_a_dict_with_changing_topology(sequence_dir):
    root, written, faces = sequence_dir
    # Frame 3 keeps only half the triangles (and the vertices they use).
    kept = faces[: len(faces) // 2]
    used, remap = np.unique(kept.reshape(-1), return_inverse=True)
    positions = written[2].reshape(-1, 3)[used]
    mesh_object("bar", positions, remap.reshape(-1, 3), {"type": "diffuse"}).write_ply(
        str(root / "frames" / "bar" / "frame_0003.ply")
    )
    description = {
        "type": "scene",
        "camera": {"type": "perspective", "film": {"type": "hdrfilm", "width": 20, "height": 20}},
        "mat": {"type": "diffuse"},
        "bar": {"type": "ply", "filename": str(root / "meshes" / "bar.ply"), "bsdf": {"type": "ref", "id": "mat"}},
        "other": {"type": "ply", "filename": str(root / "meshes" / "bar.ply"), "bsdf": {"type": "ref", "id": "mat"}},
        "sky": {"type": "constant"},
    }
    fixed = scenes.SequenceScene(description, root / "frames")
    with pytest.raises(ValueError, match=r"frame 2 of shape 'bar'.*frame_0003\.ply.*vertices"):
        fixed.frame(2)
    changing = scenes.SequenceScene(description, root / "frames", topology={"bar": "changing"})
    scene = mi.load_dict(changing.scene_dict(integrator={"type": "path"}))
    assert sorted(s.id() for s in scene.shapes()) == ["bar", "other"]
    params = mi.traverse(scene)
    for i in range(FRAMES):
        frame = changing.frame(i)
        assert frame["bar"].faces is not None
        scenes.apply_frame(scene, params, frame)
        assert scene_shape(scene, "bar").face_count() == (len(kept) if i == 2 else len(faces))
    assert np.isfinite(np.array(mi.render(scene, params))).all()


def test15_sequence_errors_name_the_file_and_the_frame(sequence_dir):
    root, _, _ = sequence_dir
    frames = root / "frames" / "bar"
    # A corrupt file: read when its frame is asked for.
    (frames / "frame_0002.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nend_header\n1 2\n")
    sequence = scenes.SequenceScene(root / "scene.xml", root / "frames")
    sequence.frame(0)
    with pytest.raises(ValueError, match=r"frame 1 of shape 'bar'.*frame_0002\.ply.*cannot read"):
        sequence.frame(1)
    truncated = (frames / "frame_0003.ply").read_bytes()
    (frames / "frame_0003.ply").write_bytes(truncated[: len(truncated) // 2])
    with pytest.raises(ValueError, match=r"frame 2 of shape 'bar'.*frame_0003\.ply"):
        sequence.frame(2)
    # A file that disappears after opening.
    (frames / "frame_0004.ply").unlink()
    with pytest.raises(ValueError, match=r"frame 3 of shape 'bar'.*frame_0004\.ply.*missing"):
        sequence.frame(3)
    # A gap: found when the sequence is opened.
    (frames / "frame_0005.ply").write_bytes((frames / "frame_0001.ply").read_bytes())
    with pytest.raises(ValueError, match=r"frame 3 of shape 'bar'.*missing file.*frame_0004\.ply"):
        scenes.SequenceScene(root / "scene.xml", root / "frames")


def test16_sequence_rejects_wrong_counts_unknown_shapes_and_bad_input(sequence_dir):
    root, written, faces = sequence_dir
    frames = root / "frames" / "bar"
    mesh_object("bar", written[1].reshape(-1, 3)[:-3], faces[:4], {"type": "diffuse"}).write_ply(
        str(frames / "frame_0002.ply")
    )
    # Same counts, other triangles (each one's winding reversed).
    mesh_object("bar", written[2].reshape(-1, 3), faces[:, ::-1], {"type": "diffuse"}).write_ply(
        str(frames / "frame_0003.ply")
    )
    sequence = scenes.SequenceScene(root / "scene.xml", root / "frames")
    with pytest.raises(ValueError, match=r"frame 1 of shape 'bar'.*frame_0002\.ply.*vertices"):
        sequence.frame(1)
    with pytest.raises(ValueError, match=r"frame 2 of shape 'bar'.*frame_0003\.ply.*faces differ"):
        sequence.frame(2)
    # Declared changing, the same files are read whole: the frame's own faces (each
    # winding reversed, as written) and positions, for the animated shape only.
    changing = scenes.SequenceScene(root / "scene.xml", root / "frames",
                                    topology="changing").frame(2)
    assert list(changing) == ["bar"]
    np.testing.assert_array_equal(np.asarray(changing["bar"].faces),
                                  np.asarray(faces)[:, ::-1].ravel())
    np.testing.assert_array_equal(np.asarray(changing["bar"].positions), written[2])
    with pytest.raises(ValueError, match="topology"):
        scenes.SequenceScene(root / "scene.xml", root / "frames", topology="wobbly")
    with pytest.raises(ValueError, match="'teapot' cannot be animated: the scene has no mesh"):
        (root / "frames" / "teapot").mkdir()
        scenes.SequenceScene(root / "scene.xml", root / "frames")
    (root / "frames" / "teapot").rmdir()
    with pytest.raises(ValueError, match="'floor' cannot be animated: Mitsuba exposes no vertex"):
        (root / "frames" / "floor").mkdir()
        scenes.SequenceScene(root / "scene.xml", root / "frames")
    (root / "frames" / "floor").rmdir()
    with pytest.raises(ValueError, match="no such file"):
        scenes.SequenceScene(root / "missing.xml", root / "frames")
    with pytest.raises(ValueError, match="no such directory"):
        scenes.SequenceScene(root / "scene.xml", root / "nowhere")
    with pytest.raises(ValueError, match="given twice"):
        shutil.copy(frames / "frame_0001.ply", frames / "frame_1.ply")
        scenes.SequenceScene(root / "scene.xml", root / "frames")


def test17_sequence_reads_obj_files(sequence_dir):
    root, written, faces = sequence_dir
    frames = root / "frames" / "bar"
    for i in range(FRAMES):
        (frames / f"frame_{i + 1:04d}.ply").unlink()
        p = written[i].reshape(-1, 3)
        lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in p.tolist()]
        lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces.tolist()]
        (frames / f"frame_{i + 1:04d}.obj").write_text("\n".join(lines) + "\n")
    sequence = scenes.SequenceScene(root / "scene.xml", root / "frames", topology="changing")
    for i in range(FRAMES):
        frame = sequence.frame(i)["bar"]
        p = np.array(frame.positions).reshape(-1, 3)
        f = np.array(frame.faces).reshape(-1, 3)
        # Mitsuba's OBJ reader may renumber vertices: compare the triangles themselves.
        assert np.array_equal(p[f], written[i].reshape(-1, 3)[faces.astype(np.int64)])


def test18_vertex_normals_match_mitsuba_and_repeat_to_the_bit():
    from hlbvh.scenes.normals import vertex_normals

    positions, faces = scene_meshes.torus(1.0, 0.3, 40, 23)
    mesh = mesh_object("torus", positions, faces, {"type": "diffuse"}, smooth=True)
    params = mi.traverse(mesh)
    ours = vertex_normals(params["vertex_positions"], params["faces"])
    for _ in range(3):
        again = vertex_normals(mi.Float(np.array(params["vertex_positions"])), params["faces"])
        assert np.array_equal(np.array(again), np.array(ours))
    # Mitsuba's own recomputation (same weighting), up to its summation order.
    plain = mi.Mesh("plain", len(positions), len(faces), has_vertex_normals=True)
    plain_params = mi.traverse(plain)
    plain_params["vertex_positions"] = params["vertex_positions"]
    plain_params["faces"] = params["faces"]
    plain_params.update()
    assert np.allclose(np.array(plain_params["vertex_normals"]), np.array(ours), atol=1e-6)
    # Outward: on a torus the normal points away from the tube's centre line.
    p = positions.reshape(-1, 3)
    ring = p.copy()
    ring[:, 2] = 0
    ring = ring / np.linalg.norm(ring, axis=1, keepdims=True) * 1.0
    n = np.array(ours).reshape(-1, 3)
    assert (np.einsum("ij,ij->i", n, p - ring) > 0.99 * 0.3).all()
