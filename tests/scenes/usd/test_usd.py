"""Animated USD stages as input (:mod:`hlbvh.scenes.usd`): stages authored here with
``pxr`` give per-frame geometry equal to what ``pxr`` itself computes (world space,
triangulated, Mitsuba's Y-up metres), render with ``accel="hlbvh"`` within the
plugin's tolerance of ``accel="native"`` frame by frame, map their cameras, lights and
materials as documented, and each bad input is one line."""

import math
import subprocess
import sys

import numpy as np
import pytest

pxr = pytest.importorskip("pxr")

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, UsdShade  # noqa: E402

from cli_helpers import read_stats, run_cli  # noqa: E402
from hlbvh import scenes  # noqa: E402
from hlbvh.render import cluster  # noqa: E402
from hlbvh.render import images  # noqa: E402
from hlbvh.errors import UserError  # noqa: E402
from hlbvh.render.source import SceneSpec, open_animation  # noqa: E402
from hlbvh.scenes.usd import UsdScene  # noqa: E402
from test_render import assert_close_to_native  # noqa: E402

TINY = ["--resolution", "24", "--spp", "2", "--quiet"]


# ---- Stages authored for the tests ----------------------------------------------------


def _quad(stage, path, corners, counts=(4,), indices=(0, 1, 2, 3), **attributes):
    """A mesh prim of ``corners`` with subdivision ``none`` unless told otherwise."""
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreatePointsAttr([Gf.Vec3f(*c) for c in corners])
    mesh.CreateFaceVertexCountsAttr(list(counts))
    mesh.CreateFaceVertexIndicesAttr(list(indices))
    mesh.CreateSubdivisionSchemeAttr(attributes.pop("scheme", "none"))
    if attributes.pop("double_sided", False):
        mesh.CreateDoubleSidedAttr(True)
    return mesh


def _preview(stage, path, **inputs):
    """A UsdPreviewSurface material at ``path`` with ``inputs`` (colours as tuples)."""
    material = UsdShade.Material.Define(stage, path)
    shader = UsdShade.Shader.Define(stage, f"{path}/Surface")
    shader.CreateIdAttr("UsdPreviewSurface")
    for name, value in inputs.items():
        kind = Sdf.ValueTypeNames.Color3f if isinstance(value, tuple) else Sdf.ValueTypeNames.Float
        shader.CreateInput(name, kind).Set(value)
    material.CreateSurfaceOutput().ConnectToSource(shader.ConnectableAPI(), "surface")
    return material


def _bind(prim, material):
    UsdShade.MaterialBindingAPI.Apply(prim.GetPrim()).Bind(material)


def write_shot(path):
    """A Y-up stage in metres, time codes 1..3: a ground (static, grey default), a
    flag whose points are time-sampled (principled), a pentagon and a quad under a
    parent whose translation is time-sampled (rigid; displayColor, emissive), a
    prototype instanced twice (a mask material), a time-sampled camera, and every
    UsdLux light kind (the dome untextured). Returns the path."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetStartTimeCode(1)
    stage.SetEndTimeCode(3)
    stage.SetTimeCodesPerSecond(24)
    UsdGeom.Xform.Define(stage, "/World")
    _quad(stage, "/World/Ground", [(-3, 0, -3), (3, 0, -3), (3, 0, 3), (-3, 0, 3)],
          indices=(0, 3, 2, 1))
    flag = _quad(stage, "/World/Flag", [(0, 0, 0)] * 6, counts=(4, 4),
                 indices=(0, 1, 4, 3, 1, 2, 5, 4), scheme="catmullClark", double_sided=True)
    for t in (1, 2, 3):
        flag.GetPointsAttr().Set([Gf.Vec3f(-1, 0.5, 0), Gf.Vec3f(0, 0.5, 0.15 * t),
                                  Gf.Vec3f(1, 0.5, 0), Gf.Vec3f(-1, 1.5, 0),
                                  Gf.Vec3f(0, 1.5, 0.15 * t), Gf.Vec3f(1, 1.5, -0.1 * t)], t)
    _bind(flag, _preview(stage, "/World/Looks/Cloth", diffuseColor=(0.2, 0.4, 0.8),
                         roughness=0.3, metallic=0.2))
    mover = UsdGeom.Xform.Define(stage, "/World/Mover")
    mover.AddRotateYOp().Set(20.0)
    translate = mover.AddTranslateOp()
    for t in (1, 2, 3):
        translate.Set(Gf.Vec3d(-1.5 + 0.3 * t, 0.0, 1.0), t)
    pentagon = _quad(stage, "/World/Mover/Pentagon",
                     [(0, 0, 0), (0.5, 0, 0), (0.6, 0.4, 0), (0.25, 0.7, 0), (-0.1, 0.4, 0)],
                     counts=(5,), indices=(0, 1, 2, 3, 4))
    pentagon.CreateDisplayColorPrimvar().Set([(0.8, 0.2, 0.1)])
    lamp = _quad(stage, "/World/Mover/Lamp", [(0.7, 0, 0), (0.9, 0, 0), (0.9, 0.2, 0),
                                              (0.7, 0.2, 0)])
    _bind(lamp, _preview(stage, "/World/Looks/Glow", emissiveColor=(2.0, 1.5, 1.0)))
    stage.CreateClassPrim("/Prototypes")  # abstract: renders only through its instances
    prototype = stage.DefinePrim("/Prototypes/Tile", "Xform")
    tile = _quad(stage, "/Prototypes/Tile/Geom", [(0, 0, 0), (0.4, 0, 0), (0.4, 0.4, 0),
                                                  (0, 0.4, 0)])
    _bind(tile, _preview(stage, "/Prototypes/Tile/Veil", diffuseColor=(0.1, 0.7, 0.2),
                         opacity=0.6))
    for k, x in enumerate((1.2, 1.8)):
        instance = UsdGeom.Xform.Define(stage, f"/World/Tile_{k}")
        instance.AddTranslateOp().Set(Gf.Vec3d(x, 0.1, 0.8))
        instance.GetPrim().GetReferences().AddInternalReference(prototype.GetPath())
        instance.GetPrim().SetInstanceable(True)
    camera = UsdGeom.Camera.Define(stage, "/World/Cam")
    move = camera.AddTranslateOp()
    move.Set(Gf.Vec3d(0, 1.2, 6), 1)
    move.Set(Gf.Vec3d(0.5, 1.2, 6), 3)
    camera.CreateFocalLengthAttr(30.0)
    sun = UsdLux.DistantLight.Define(stage, "/World/Lights/Sun")
    sun.CreateIntensityAttr(1.5)
    sun.CreateExposureAttr(1.0)
    sun.CreateColorAttr(Gf.Vec3f(1.0, 0.9, 0.8))
    sun.CreateNormalizeAttr(True)  # its intensity is the irradiance
    sun.AddRotateXOp().Set(-50.0)
    UsdLux.DomeLight.Define(stage, "/World/Lights/Sky").CreateIntensityAttr(0.2)
    sphere = UsdLux.SphereLight.Define(stage, "/World/Lights/Bulb")
    sphere.CreateRadiusAttr(0.2)
    sphere.CreateIntensityAttr(3.0)
    sphere.AddTranslateOp().Set(Gf.Vec3d(-2, 2, 1))
    point = UsdLux.SphereLight.Define(stage, "/World/Lights/Spark")
    point.CreateTreatAsPointAttr(True)
    point.CreateIntensityAttr(4.0)
    point.AddTranslateOp().Set(Gf.Vec3d(2, 2, 2))
    rect = UsdLux.RectLight.Define(stage, "/World/Lights/Panel")
    rect.CreateWidthAttr(1.0)
    rect.CreateHeightAttr(0.5)
    rect.CreateIntensityAttr(2.0)
    rect.AddTranslateOp().Set(Gf.Vec3d(0, 3, 0))
    rect.AddRotateXOp().Set(-90.0)  # -Z (its emitting side) turned to face down
    disk = UsdLux.DiskLight.Define(stage, "/World/Lights/Disk")
    disk.CreateRadiusAttr(0.3)
    disk.CreateIntensityAttr(2.0)
    disk.AddTranslateOp().Set(Gf.Vec3d(2.5, 2.5, 0))
    disk.AddRotateXOp().Set(-90.0)
    stage.GetRootLayer().Save()
    return path


def write_z_up(path, texture=None):
    """A Z-up stage in centimetres, time codes 0..1: a ground, a post 150 cm tall
    whose top point moves, a dome (textured when ``texture`` is a file), no camera."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    stage.SetStartTimeCode(0)
    stage.SetEndTimeCode(1)
    _quad(stage, "/Ground", [(-200, -200, 0), (200, -200, 0), (200, 200, 0), (-200, 200, 0)])
    post = _quad(stage, "/Post", [(0, 0, 0)] * 3, counts=(3,), indices=(0, 1, 2),
                 double_sided=True)
    for t in (0, 1):
        post.GetPointsAttr().Set([Gf.Vec3f(-30, 0, 0), Gf.Vec3f(30, 0, 0),
                                  Gf.Vec3f(10 * t, 0, 150)], t)
    painted = _quad(stage, "/Painted", [(60, 0, 0), (120, 0, 0), (120, 0, 60), (60, 0, 60)])
    painted.CreateDisplayColorPrimvar(UsdGeom.Tokens.vertex).Set(
        [(1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 0)])
    banner = _quad(stage, "/Banner", [(-120, 0, 0), (-60, 0, 0), (-60, 0, 60), (-120, 0, 60),
                                      (-90, 0, 90)], counts=(4, 3), indices=(0, 1, 2, 3, 3, 2, 4))
    banner.CreateDisplayColorPrimvar(UsdGeom.Tokens.uniform).Set([(0.9, 0.5, 0.1),
                                                                  (0.1, 0.3, 0.9)])
    dome = UsdLux.DomeLight.Define(stage, "/Sky")
    dome.CreateIntensityAttr(0.8)
    if texture is not None:
        dome.CreateTextureFileAttr(Sdf.AssetPath(str(texture)))
    stage.GetRootLayer().Save()
    return path


# ---- What pxr says, computed here independently -------------------------------------


def pxr_triangles(stage_path, time):
    """Every rendered mesh's triangles at ``time`` per prim path, ``(F, 3, 3)`` corners
    in the stage's own units and axes: points through ``ComputeLocalToWorldTransform``,
    polygons cut into fans one by one."""
    stage = Usd.Stage.Open(str(stage_path))
    result = {}
    predicate = Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)
    for prim in Usd.PrimRange(stage.GetPseudoRoot(), predicate):
        if not prim.IsA(UsdGeom.Mesh):
            continue
        mesh = UsdGeom.Mesh(prim)
        matrix = UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(time)
        points = [matrix.Transform(Gf.Vec3d(p)) for p in mesh.GetPointsAttr().Get(time)]
        triangles, offset = [], 0
        indices = list(mesh.GetFaceVertexIndicesAttr().Get(time))
        for count in mesh.GetFaceVertexCountsAttr().Get(time):
            face = indices[offset:offset + count]
            offset += count
            for k in range(1, count - 1):
                triangles.append([list(points[face[0]]), list(points[face[k]]),
                                  list(points[face[k + 1]])])
        result[str(prim.GetPath())] = np.array(triangles)
    return result


def mitsuba_triangles(scene, groups=None):
    """Every triangle mesh of a loaded Mitsuba scene (not the analytic shapes of area
    lights) as ``(F, 3, 3)`` corners, by id; an instance's (``groups``: its group's id,
    by instance id) its group's meshes through its ``to_world``, read from Mitsuba."""
    params = mi.traverse(scene)
    result = {}
    for shape in scene.shapes():
        if f"{shape.id()}.vertex_positions" in params:
            points = np.array(params[f"{shape.id()}.vertex_positions"]).reshape(-1, 3)
            faces = np.array(params[f"{shape.id()}.faces"]).reshape(-1, 3)
            result[shape.id()] = points[faces]
        elif groups and shape.id() in groups:
            m = np.array(params[f"{shape.id()}.to_world"].matrix, np.float64).reshape(4, 4)
            members = [k[:-len(".vertex_positions")] for k in params.keys()
                       if k.startswith(groups[shape.id()] + ".") and k.endswith(".vertex_positions")]
            result[shape.id()] = np.concatenate([
                (np.array(params[f"{k}.vertex_positions"]).reshape(-1, 3) @ m[:3, :3].T
                 + m[:3, 3])[np.array(params[f"{k}.faces"]).reshape(-1, 3)] for k in members])
    return result


def rendered_meshes(animation):
    """Each mesh's id and what the loader made of it: a world-space mesh, or for an
    instance its group's first part (its BSDF, colours, texture coordinates)."""
    meshes = {m.id: m for m in animation._meshes}
    meshes.update({i.id: i.group.parts[0] for i in animation._instances})
    return meshes


@pytest.fixture(scope="module")
def shot(tmp_path_factory):
    return write_shot(tmp_path_factory.mktemp("usd") / "shot.usda")


def lines():
    """A warning sink: the list it fills and the callable."""
    said = []
    return said, said.append


# ---- Geometry and motion ----------------------------------------------------------------


def test01_each_frame_holds_what_pxr_computes_world_space_and_triangulated(shot):
    said, warn = lines()
    animation = UsdScene(shot, warn=warn)
    assert animation.frame_count == 3 and animation.frames_per_second == 24
    assert animation.motions() == {
        "World_Ground": "static", "World_Flag": "deforming",
        "World_Mover_Pentagon": "rigid", "World_Mover_Lamp": "rigid",
        "World_Tile_0_Geom": "static", "World_Tile_1_Geom": "static"}
    assert animation.animated_ids() == ["World_Flag", "World_Mover_Pentagon",
                                        "World_Mover_Lamp"]
    assert sorted(animation.static_ids()) == ["World_Ground", "World_Tile_0_Geom",
                                              "World_Tile_1_Geom"]
    assert animation.triangle_counts()["World_Mover_Pentagon"] == 3
    assert animation.prim_paths()["World_Tile_1_Geom"] == "/World/Tile_1/Geom"
    scene = mi.load_dict(animation.scene_dict(resolution=(8, 8), spp=1))
    params = mi.traverse(scene)
    paths = animation.prim_paths()
    for i in range(animation.frame_count):
        changed = scenes.apply_frame(scene, params, animation.frame(i))
        assert changed == animation.animated_ids()
        expected = pxr_triangles(shot, Usd.TimeCode(1 + i))
        ours = mitsuba_triangles(scene, animation.instance_groups())
        assert set(ours) == set(paths)
        for shape_id, triangles in ours.items():
            np.testing.assert_allclose(triangles, expected[paths[shape_id]], atol=1e-5,
                                       err_msg=f"{shape_id} at frame {i}")
        for shape_id, triangles in animation.world_triangles(i).items():
            np.testing.assert_allclose(triangles, expected[paths[shape_id]], atol=1e-9)
    # The two instances are one prototype, one shape group, each in its own place; the
    # rigid pentagon an instance too (its frames move its transform), the emitting lamp
    # a world-space mesh (Mitsuba refuses emitters inside shape groups)
    groups = animation.instance_groups()
    assert set(groups) == {"World_Tile_0_Geom", "World_Tile_1_Geom"}
    assert groups["World_Tile_0_Geom"] == groups["World_Tile_1_Geom"]
    # (the pentagon: three triangles, rewritten in world space, cheaper than a group)
    assert animation.frame(1)["World_Mover_Pentagon"].positions is not None
    tiles = mitsuba_triangles(scene, groups)
    np.testing.assert_allclose(tiles["World_Tile_1_Geom"] - tiles["World_Tile_0_Geom"],
                               np.broadcast_to([0.6, 0, 0], (2, 3, 3)), atol=1e-6)
    # Said once: the control cage.
    assert sum("subdivision scheme" in line and "/World/Flag" in line for line in said) == 1


def test02_z_up_centimetres_are_y_up_metres_and_upright(tmp_path):
    path = write_z_up(tmp_path / "z.usda")
    said, warn = lines()
    animation = UsdScene(path, warn=warn)
    assert [line for line in said if "default camera" in line]
    for i in range(2):
        triangles = animation.world_triangles(i)
        stage_units = pxr_triangles(path, Usd.TimeCode(i))
        for shape_id, prim in animation.prim_paths().items():
            x, y, z = np.moveaxis(stage_units[prim], -1, 0)
            np.testing.assert_allclose(triangles[shape_id],
                                       np.stack([x, z, -y], axis=-1) * 0.01, atol=1e-9)
    meshes = rendered_meshes(animation)
    assert list(meshes["Painted"].attributes) == ["vertex_color"]
    np.testing.assert_allclose(meshes["Painted"].attributes["vertex_color"][2], [0, 0, 1])
    (name, per_triangle), = meshes["Banner"].attributes.items()
    assert name == "face_color"
    np.testing.assert_allclose(per_triangle, [[0.9, 0.5, 0.1]] * 2 + [[0.1, 0.3, 0.9]],
                               rtol=1e-6)
    top = animation.frame(1)["Post"].positions.reshape(-1, 3)[2]
    np.testing.assert_allclose(top, [0.1, 1.5, 0.0], atol=1e-6)  # 150 cm up is +y
    camera = animation.scene_dict(resolution=(16, 16), spp=1)["camera"]
    up = np.array(camera["to_world"].matrix)[:3, 1]
    assert up[1] > 0.8  # the framing camera stands upright


# ---- Renders equal native's ------------------------------------------------------------


def render_both(capsys, stage, root, frames="0:2"):
    """``hlbvh render STAGE`` with each accelerator: their output folders."""
    folders = {}
    for accel in ("hlbvh", "native"):
        status, _, err = run_cli(capsys, "render", stage, "--frames", frames,
                                 "--accel", accel, "--out", root / accel, *TINY)
        assert status == 0, err
        folders[accel] = root / accel
    return folders


def assert_frames_agree(folders, frames):
    for i in frames:
        ours = images.read_exr(folders["hlbvh"] / f"frame_{i:04d}.exr", ["R", "G", "B"])
        native = images.read_exr(folders["native"] / f"frame_{i:04d}.exr", ["R", "G", "B"])
        assert np.isfinite(ours).all() and ours.mean() > 0.01
        assert_close_to_native(ours, native)


def test03_shot_renders_with_hlbvh_as_native_frame_by_frame_and_resumes(shot, tmp_path,
                                                                       capsys):
    folders = render_both(capsys, shot, tmp_path)
    assert_frames_agree(folders, range(2))
    document, _ = read_stats(folders["hlbvh"])
    assert document["settings"]["scene"] == str(shot.resolve())
    assert len(document["settings"]["scene_sha256"]) == 64
    first = images.read_exr(folders["hlbvh"] / "frame_0000.exr", ["R", "G", "B"])
    second = images.read_exr(folders["hlbvh"] / "frame_0001.exr", ["R", "G", "B"])
    assert not np.array_equal(first, second)  # the flag and the mover moved
    status, summary, _ = run_cli(capsys, "render", shot, "--frames", "0:2", "--accel",
                                 "hlbvh", "--out", folders["hlbvh"], *TINY)
    assert status == 0 and "0 rendered, 2 already complete" in summary


def test04_z_up_stage_with_a_textured_dome_renders_as_native(tmp_path, capsys):
    texture = tmp_path / "sky.exr"
    sky = (np.ones((8, 16, 3)) * np.linspace(0.2, 1.0, 8)[:, None, None]).astype(np.float32)
    mi.Bitmap(sky).write(str(texture))
    path = write_z_up(tmp_path / "z.usda", texture=texture)
    description = UsdScene(path, warn=lambda line: None).scene_dict(spp=1)
    assert description["Sky"]["type"] == "envmap"
    assert description["Sky"]["filename"] == str(texture)
    assert description["Sky"]["scale"] == pytest.approx(0.8)
    folders = render_both(capsys, path, tmp_path / "out")
    assert_frames_agree(folders, range(2))


# ---- Cameras, lights, materials ------------------------------------------------------


def test05_camera_fov_clipping_and_a_moving_pose_unsaid(shot):
    said, warn = lines()
    animation = UsdScene(shot, warn=warn)
    camera = animation.scene_dict(resolution=(40, 20), spp=1)["camera"]
    gf_camera = UsdGeom.Camera(animation.stage.GetPrimAtPath("/World/Cam")).GetCamera(1)
    # A film wider than the aperture (2:1 > 20.955:15.29) fits the aperture's height.
    assert camera["fov_axis"] == "y"
    assert camera["fov"] == pytest.approx(
        2 * math.degrees(math.atan(gf_camera.verticalAperture / 2 / 30.0)))
    assert (camera["near_clip"], camera["far_clip"]) == pytest.approx(
        (gf_camera.clippingRange.min, gf_camera.clippingRange.max))
    matrix = np.array(camera["to_world"].matrix)
    np.testing.assert_allclose(matrix[:3, 3], [0, 1.2, 6], atol=1e-6)   # time code 1
    np.testing.assert_allclose(matrix[:3, 2], [0, 0, -1], atol=1e-6)    # looks down -Z
    narrow = animation.scene_dict(resolution=(10, 20), spp=1)["camera"]
    assert narrow["fov_axis"] == "x" and narrow["fov"] == pytest.approx(
        2 * math.degrees(math.atan(gf_camera.horizontalAperture / 2 / 30.0)))
    assert not [line for line in said if "/World/Cam" in line]  # the frames move it
    other = write_shot_camera(shot.parent / "two_cameras.usda")
    chosen = UsdScene(other, camera="/Other", warn=warn).scene_dict(spp=1)["camera"]
    np.testing.assert_allclose(np.array(chosen["to_world"].matrix)[:3, 3], [3, 1, 3],
                               atol=1e-6)
    with pytest.raises(ValueError, match="camera '/Nope'.*its cameras"):
        UsdScene(other, camera="/Nope", warn=warn)


def write_shot_camera(path):
    """A small stage with two cameras, the second at (3, 1, 3)."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    _quad(stage, "/Q", [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)])
    UsdGeom.Camera.Define(stage, "/First").AddTranslateOp().Set(Gf.Vec3d(0, 0, 5))
    UsdGeom.Camera.Define(stage, "/Other").AddTranslateOp().Set(Gf.Vec3d(3, 1, 3))
    UsdLux.DomeLight.Define(stage, "/Sky")
    stage.GetRootLayer().Save()
    return path


def test06_lights_map_to_mitsuba_emitters(shot):
    description = UsdScene(shot, warn=lambda line: None).scene_dict(spp=1)
    sun = description["World_Lights_Sun"]
    assert sun["type"] == "directional"
    np.testing.assert_allclose(sun["irradiance"]["value"], [3.0, 2.7, 2.4], rtol=1e-6)
    np.testing.assert_allclose(sun["direction"], [0, -math.sin(math.radians(50)),
                                                  -math.cos(math.radians(50))], atol=1e-9)
    assert description["World_Lights_Sky"]["type"] == "constant"
    bulb = description["World_Lights_Bulb"]
    assert bulb["type"] == "sphere" and bulb["radius"] == pytest.approx(0.2)
    assert bulb["center"] == pytest.approx([-2, 2, 1])
    assert description["World_Lights_Spark"]["type"] == "point"
    panel, disk = description["World_Lights_Panel"], description["World_Lights_Disk"]
    assert (panel["type"], disk["type"]) == ("rectangle", "disk")
    loaded = mi.load_dict({"type": "scene", "panel": panel, "disk": disk})
    shapes = {s.id(): s for s in loaded.shapes()}
    # The panel emits downwards (UsdLux: along -Z, turned by its rotateX -90).
    normal = np.array(panel["to_world"] @ mi.ScalarNormal3f(0, 0, 1))
    np.testing.assert_allclose(normal / np.linalg.norm(normal), [0, -1, 0], atol=1e-6)
    assert shapes["panel"].surface_area()[0] == pytest.approx(0.5, rel=1e-5)
    assert shapes["disk"].surface_area()[0] == pytest.approx(math.pi * 0.09, rel=1e-5)


def test07_materials_map_to_mitsuba_bsdfs(shot):
    animation = UsdScene(shot, warn=lambda line: None)
    meshes = rendered_meshes(animation)
    flag = meshes["World_Flag"].bsdf
    assert flag["type"] == "principled"  # both sides at load, as every USD mesh
    assert flag["base_color"]["value"] == pytest.approx([0.2, 0.4, 0.8])
    assert flag["roughness"] == pytest.approx(0.3)
    assert flag["metallic"] == pytest.approx(0.2)
    tile = meshes["World_Tile_0_Geom"].bsdf
    assert tile["type"] == "mask" and tile["opacity"] == pytest.approx(0.6)
    assert meshes["World_Mover_Lamp"].emission == pytest.approx((2.0, 1.5, 1.0))
    assert meshes["World_Mover_Pentagon"].bsdf["reflectance"]["value"] == pytest.approx(
        [0.8, 0.2, 0.1])
    assert meshes["World_Ground"].bsdf["reflectance"]["value"] == [0.5, 0.5, 0.5]
    scene = mi.load_dict(animation.scene_dict(resolution=(8, 8), spp=1))
    emitting = [s.id() for s in scene.shapes() if s.emitter() is not None]
    assert "World_Mover_Lamp" in emitting


# ---- What is not supported, and bad input: one line each ------------------------------


def test08_unsupported_prims_and_broken_references_are_named_once(tmp_path):
    path = tmp_path / "mixed.usda"
    stage = Usd.Stage.CreateNew(str(path))
    _quad(stage, "/Q", [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)])
    UsdGeom.BasisCurves.Define(stage, "/Hair")
    UsdGeom.Points.Define(stage, "/Dust")
    UsdGeom.PointInstancer.Define(stage, "/Scatter")
    _quad(stage, "/Scatter/Prototypes/Pebble", [(0, 0, 0), (1, 0, 0), (1, 1, 0)],
          counts=(3,), indices=(0, 1, 2))
    blinking = _quad(stage, "/Blinking", [(0, 0, 0), (1, 0, 0), (1, 1, 0)], counts=(3,),
                     indices=(0, 1, 2))
    blinking.CreateVisibilityAttr().Set(UsdGeom.Tokens.invisible, 0)
    blinking.GetVisibilityAttr().Set(UsdGeom.Tokens.inherited, 1)
    hidden = _quad(stage, "/Hidden", [(0, 0, 0), (1, 0, 0), (1, 1, 0)], counts=(3,),
                   indices=(0, 1, 2))
    hidden.CreateVisibilityAttr(UsdGeom.Tokens.invisible)
    guide = _quad(stage, "/Guide", [(0, 0, 0), (1, 0, 0), (1, 1, 0)], counts=(3,),
                  indices=(0, 1, 2))
    guide.CreatePurposeAttr(UsdGeom.Tokens.guide)
    stage.DefinePrim("/Ref").GetReferences().AddReference(str(tmp_path / "missing.usda"))
    warm = UsdLux.SphereLight.Define(stage, "/Warm")
    warm.CreateEnableColorTemperatureAttr(True)
    UsdLux.ShapingAPI.Apply(warm.GetPrim()).CreateShapingConeAngleAttr(30.0)
    UsdLux.CylinderLight.Define(stage, "/Tube")
    stage.GetRootLayer().Save()
    said, warn = lines()
    animation = UsdScene(path, warn=warn)
    # Hidden and guide prims do not render, nor a point instancer's prototypes.
    assert animation.static_ids() == ["Q"]
    for prim in ("/Hair", "/Dust", "/Ref", "/Scatter", "/Blinking", "/Tube"):
        assert sum(prim in line for line in said) == 1, (prim, said)
    assert sum("/Warm" in line and "temperature" in line for line in said) == 1
    assert sum("/Warm" in line and "shaping" in line for line in said) == 1
    assert all(line.startswith(f"stage {str(path)!r}: ") for line in said)
    assert not any("/Hidden" in line or "/Guide" in line for line in said)


def write_empty(path):
    stage = Usd.Stage.CreateNew(str(path))
    stage.GetRootLayer().Save()
    return path


@pytest.mark.parametrize("case, message", [
    ("not_usd", "USD cannot open it"),
    ("empty", "nothing renderable"),
    ("reversed", "endTimeCode 1 is before startTimeCode 5"),
    ("out_of_range", "has frames 0:3 (time codes 1..3, startTimeCode..endTimeCode)"),
    ("missing", "no such file"),
    ("broken_reference", "nothing renderable (no visible UsdGeom.Mesh of purpose default or "
                         "render); references or payloads that do not resolve: /Set (Could "
                         "not open asset @"),
])
def test09_bad_stages_are_one_line_through_the_cli(tmp_path, capsys, shot, case, message):
    if case == "not_usd":
        stage = tmp_path / "fake.usd"
        stage.write_bytes(b"PK\x03\x04 this is a zip, not a stage")
    elif case == "empty":
        stage = write_empty(tmp_path / "empty.usda")
    elif case == "reversed":
        stage = tmp_path / "reversed.usda"
        created = Usd.Stage.CreateNew(str(stage))
        _quad(created, "/Q", [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)])
        created.SetStartTimeCode(5)
        created.SetEndTimeCode(1)
        created.GetRootLayer().Save()
    elif case == "missing":
        stage = tmp_path / "gone.usdc"
    elif case == "broken_reference":
        stage = tmp_path / "shot.usda"
        created = Usd.Stage.CreateNew(str(stage))
        created.DefinePrim("/Set").GetReferences().AddReference("./set_v2.usda")
        created.GetRootLayer().Save()
    else:
        stage = shot
    frames = "0:9" if case == "out_of_range" else "0:1"
    status, _, err = run_cli(capsys, "render", stage, "--frames", frames,
                             "--out", tmp_path / "out", *TINY)
    assert status == 2 and len(err) == 1 and message in err[0], err
    assert "Traceback" not in "".join(err)


def test10_usd_options_that_do_not_apply_are_refused(shot):
    with pytest.raises(UserError, match="--frames-dir is not for USD stages"):
        open_animation(SceneSpec(str(shot), frames_dir="frames"))
    with pytest.raises(UserError, match="--triangles is not for USD stages"):
        open_animation(SceneSpec(str(shot), triangles="100"))


def test11_a_cluster_worker_reopens_the_stage_from_its_spec(shot, monkeypatch):
    monkeypatch.chdir(shot.parent)
    spec = SceneSpec.of(shot.name, None, None, range(0, 2)).absolute()
    assert spec.scene == str(shot.resolve())
    animation, _, frames = open_animation(spec)
    assert isinstance(animation, UsdScene) and frames == range(0, 2)


def test12_console_script_reports_a_bad_stage_without_traceback(tmp_path):
    fake = tmp_path / "fake.usda"
    fake.write_text("#usda 1.0\n( this is not a layer\n")
    result = subprocess.run([sys.executable, "-m", "hlbvh.cli", "render", str(fake),
                             "--out", str(tmp_path / "out")],
                            capture_output=True, text=True, timeout=120)
    lines_out = [line for line in result.stderr.splitlines() if line.strip()]
    assert result.returncode == 2 and len(lines_out) == 1, result.stderr
    assert str(fake) in lines_out[0] and "USD cannot open it" in lines_out[0]


def test13_render_settings_name_the_camera_and_resolution(tmp_path):
    path = write_shot_camera(tmp_path / "settings.usda")
    stage = Usd.Stage.Open(str(path))
    from pxr import UsdRender
    settings = UsdRender.Settings.Define(stage, "/Render/Settings")
    settings.CreateCameraRel().SetTargets([Sdf.Path("/Other")])
    settings.CreateResolutionAttr(Gf.Vec2i(30, 20))
    stage.SetMetadata("renderSettingsPrimPath", "/Render/Settings")
    stage.GetRootLayer().Save()
    description = UsdScene(path, warn=lambda line: None).scene_dict(spp=1)
    camera = description["camera"]
    np.testing.assert_allclose(np.array(camera["to_world"].matrix)[:3, 3], [3, 1, 3],
                               atol=1e-6)
    assert (camera["film"]["width"], camera["film"]["height"]) == (30, 20)


def test14_authored_vertex_normals_are_kept_and_face_varying_ones_said(tmp_path):
    path = tmp_path / "normals.usda"
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    parent = UsdGeom.Xform.Define(stage, "/Turned")
    parent.AddRotateZOp().Set(90.0)
    parent.AddScaleOp().Set(Gf.Vec3f(2, 1, 1))
    tilted = _quad(stage, "/Turned/Tilted", [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)])
    tilted.CreateNormalsAttr([Gf.Vec3f(0, 0, 1), Gf.Vec3f(1, 0, 1), Gf.Vec3f(0, 1, 1),
                              Gf.Vec3f(0, 0, 1)])
    tilted.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    faceted = _quad(stage, "/Faceted", [(0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)])
    faceted.CreateNormalsAttr([Gf.Vec3f(0, 0, 1)] * 4)
    faceted.SetNormalsInterpolation(UsdGeom.Tokens.faceVarying)
    stage.GetRootLayer().Save()
    said, warn = lines()
    scene = mi.load_dict(UsdScene(path, warn=warn).scene_dict(resolution=(8, 8), spp=1))
    normals = np.array(mi.traverse(scene)["Turned_Tilted.vertex_normals"]).reshape(-1, 3)
    matrix = np.array(UsdGeom.Xformable(stage.GetPrimAtPath("/Turned/Tilted"))
                      .ComputeLocalToWorldTransform(0)).T[:3, :3]
    authored = np.array(tilted.GetNormalsAttr().Get()) @ np.linalg.inv(matrix)
    np.testing.assert_allclose(normals, authored / np.linalg.norm(authored, axis=1)[:, None],
                               atol=1e-6)
    assert sum("not per vertex" in line and "/Faceted" in line for line in said) == 1


def test15_compare_on_a_stage_reports_native_and_hlbvh_equal(shot, tmp_path, capsys):
    status, summary, _ = run_cli(capsys, "compare", shot, "--frames", "0:2",
                                 "--out", tmp_path / "compare", *TINY)
    assert status == 0 and "within Monte Carlo noise of native's on every frame" in summary
    assert (tmp_path / "compare" / "report.html").is_file()


def test16_a_local_cluster_renders_a_stage_as_one_process(shot, tmp_path, capsys):
    pytest.importorskip("distributed")
    # bit for bit when the moving meshes' structure is named (under "auto" each process
    # chooses by its own timings)
    argv = [shot, "--frames", "0:2", "--accel", "hlbvh", "--moving-accel", "hlbvh", *TINY]
    assert run_cli(capsys, "render", *argv, "--out", tmp_path / "one")[0] == 0
    status, _, err = run_cli(capsys, "render", *argv, "--cluster", "local:2",
                             "--chunk-size", "1", "--out", tmp_path / "cluster")
    assert status == 0, err
    for i in range(2):
        ours = images.read_exr(tmp_path / "cluster" / f"frame_{i:04d}.exr").view(np.uint32)
        alone = images.read_exr(tmp_path / "one" / f"frame_{i:04d}.exr").view(np.uint32)
        assert np.array_equal(ours, alone), f"frame {i}"
    _, table = read_stats(tmp_path / "cluster")
    assert [int(row["frame"]) for row in table] == [0, 1] and all(row["worker"] for row in table)


@pytest.mark.parametrize("before", [True, False])
def test17_camera_flag_picks_the_camera_and_travels_to_cluster_specs(tmp_path, capsys,
                                                                     before):
    from hlbvh.cli import render
    import argparse
    path = write_shot_camera(tmp_path / "cams.usda")
    parser = argparse.ArgumentParser()
    render.configure(parser)
    argv = ["--camera", "/Other", str(path)] if before else [str(path), "--camera", "/Other"]
    args = parser.parse_args(argv)
    animation, source, _ = open_animation(SceneSpec.of(args.scene))
    assert source["camera"] == "/Other"
    camera = animation.scene_dict(spp=1)["camera"]
    np.testing.assert_allclose(np.array(camera["to_world"].matrix)[:3, 3], [3, 1, 3],
                               atol=1e-6)
    spec = SceneSpec.of(args.scene, None, None, range(0, 1)).absolute()
    assert spec.camera == "/Other" and type(spec.scene) is str
    status, _, err = run_cli(capsys, "render", path, "--camera", "/Nope", "--out",
                             tmp_path / "x", *TINY)
    assert status == 2 and len(err) == 1 and "camera '/Nope'" in err[0]
    status, _, err = run_cli(capsys, "render", "cloth", "--camera", "/Cam", "--out",
                             tmp_path / "y", *TINY)
    assert status == 2 and err == ["hlbvh render: --camera picks a camera of a USD stage; "
                                   "'cloth' is not one"]


def test18_crate_and_package_stages_open_and_skinned_meshes_are_said(tmp_path):
    from pxr import UsdSkel, UsdUtils
    crate = tmp_path / "shot.usdc"
    stage = Usd.Stage.CreateNew(str(crate))
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    mesh = _quad(stage, "/Body", [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)])
    UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    stage.GetRootLayer().Save()
    package = tmp_path / "shot.usdz"
    assert UsdUtils.CreateNewUsdzPackage(str(crate), str(package))
    digests = []
    for path in (crate, package):
        said, warn = lines()
        animation = UsdScene(path, warn=warn)
        assert animation.static_ids() == ["Body"]
        assert sum("/Body" in line and "UsdSkel" in line for line in said) == 1
        digests.append(animation.source_digest())
    mesh.GetPointsAttr().Set([Gf.Vec3f(0, 0, 0), Gf.Vec3f(2, 0, 0), Gf.Vec3f(2, 1, 0),
                              Gf.Vec3f(0, 1, 0)])
    stage.GetRootLayer().Save()
    assert UsdUtils.CreateNewUsdzPackage(str(crate), str(package))
    # The package's digest follows its bytes (its layers are inside it).
    assert UsdScene(package, warn=lambda line: None).source_digest() != digests[1]


def test19_dome_poles_follow_usdlux(tmp_path):
    texture = tmp_path / "sky.exr"
    mi.Bitmap(np.ones((4, 8, 3), dtype=np.float32)).write(str(texture))
    path = tmp_path / "domes.usda"
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    _quad(stage, "/Q", [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)])
    for kind, name in ((UsdLux.DomeLight, "/Old"), (UsdLux.DomeLight_1, "/New")):
        kind.Define(stage, name).CreateTextureFileAttr(Sdf.AssetPath(str(texture)))
    stage.GetRootLayer().Save()
    description = UsdScene(path, warn=lambda line: None).scene_dict(spp=1)
    pole = {name: np.array(description[name]["to_world"].matrix)[:3, :3] @ [0, 1, 0]
            for name in ("Old", "New")}
    # DomeLight: the pole is the stage's +Y (Mitsuba's -Z after Z-up -> Y-up);
    # DomeLight_1 with poleAxis "scene": the stage's up axis, Mitsuba's +Y.
    np.testing.assert_allclose(pole["Old"], [0, 0, -1], atol=1e-9)
    np.testing.assert_allclose(pole["New"], [0, 1, 0], atol=1e-9)


def test20_holes_left_handed_faces_subsets_and_growing_point_counts(tmp_path):
    path = tmp_path / "odd.usda"
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetStartTimeCode(0)
    stage.SetEndTimeCode(1)
    corners = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (2, 0, 0), (2, 1, 0)]
    left = _quad(stage, "/Left", corners, counts=(4, 4, 2, 3),
                 indices=(0, 1, 2, 3, 1, 4, 5, 2, 0, 1, 1, 4, 5))
    left.CreateOrientationAttr(UsdGeom.Tokens.leftHanded)
    left.CreateHoleIndicesAttr([1])
    red = UsdGeom.Subset.CreateGeomSubset(left, "red", UsdGeom.Tokens.face, [0],
                                          familyName="materialBind")
    _bind(red, _preview(stage, "/Looks/Red", diffuseColor=(0.9, 0.1, 0.1)))
    _bind(left, _preview(stage, "/Looks/Blue", diffuseColor=(0.1, 0.1, 0.9)))
    growing = _quad(stage, "/Growing", [(0, 0, 0)] * 3, counts=(3,), indices=(0, 1, 2))
    growing.GetPointsAttr().Set([Gf.Vec3f(0, 0, 1), Gf.Vec3f(1, 0, 1), Gf.Vec3f(0, 1, 1)], 0)
    growing.GetPointsAttr().Set([Gf.Vec3f(0, 0, 1), Gf.Vec3f(1, 0, 1), Gf.Vec3f(0, 1, 1),
                                 Gf.Vec3f(5, 5, 5)], 1)
    stage.GetRootLayer().Save()
    said, warn = lines()
    animation = UsdScene(path, warn=warn)
    meshes = rendered_meshes(animation)
    # The hole (face 1) and the 2-vertex face are left out; left-handed faces reversed;
    # the subset's face is a mesh of its own with the subset's material, the rest keeps
    # the mesh's.
    np.testing.assert_array_equal(meshes["Left_red"].faces, [[2, 1, 0], [3, 2, 0]])
    np.testing.assert_array_equal(meshes["Left"].faces, [[5, 4, 1]])
    assert meshes["Left_red"].bsdf["base_color"]["value"] == pytest.approx([0.9, 0.1, 0.1])
    assert meshes["Left"].bsdf["base_color"]["value"] == pytest.approx([0.1, 0.1, 0.9])
    assert animation.prim_paths()["Left_red"] == "/Left"
    assert sum("/Left" in line and "fewer than 3" in line for line in said) == 1
    scene = mi.load_dict(animation.scene_dict(resolution=(8, 8), spp=1))
    params = mi.traverse(scene)
    for i in range(2):
        scenes.apply_frame(scene, params, animation.frame(i))
        assert dr.width(params["Growing.vertex_positions"]) == 3 * (3 + i)
    np.testing.assert_allclose(mitsuba_triangles(scene)["Growing"],
                               pxr_triangles(path, Usd.TimeCode(1))["/Growing"], atol=1e-6)


def test21_the_stage_s_still_meshes_are_built_once_and_never_leave(shot):
    """FrameRenderer declares the stage's deforming and rigid meshes as moving: the still
    world (ground, instances, light shapes) is built once and nothing leaves it."""
    from hlbvh.render.frame import FrameRenderer
    from hlbvh.render.settings import RenderSettings
    animation = UsdScene(shot, warn=lambda line: None)
    renderer = FrameRenderer(animation, RenderSettings(resolution=(8, 8), spp=1))
    for i in range(animation.frame_count):
        renderer.render(i)
        accel = renderer.integrator.scene_accel
        assert accel.last_update["groups"]["static"]["left"] == []
        assert sorted(accel.last_update["moving"]) == sorted(animation.animated_ids())
    assert accel.static.builds == 1


def test22_a_resume_after_the_stage_or_its_layers_changed_is_refused(tmp_path, capsys):
    layer = tmp_path / "post.usda"
    write_z_up(layer)
    shot_path = tmp_path / "shot.usda"
    stage = Usd.Stage.CreateNew(str(shot_path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    stage.GetRootLayer().subLayerPaths.append("./post.usda")
    stage.GetRootLayer().Save()
    argv = ["render", shot_path, "--frames", "0:1", "--out", tmp_path / "out", *TINY]
    assert run_cli(capsys, *argv)[0] == 0
    layer.write_text(layer.read_text().replace("150", "140"))  # the sublayer is edited
    status, _, err = run_cli(capsys, *argv)
    refusals = [line for line in err if not line.startswith("hlbvh: stage")]
    assert status == 2 and len(refusals) == 1 and "scene_sha256" in refusals[0]


def write_textured(path, texture, frames=2):
    """A stage in metres: a deforming 2-quad strip facing the camera with faceVarying
    (indexed) st and a UsdUVTexture on its diffuseColor; the texture ``texture``."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetStartTimeCode(0)
    stage.SetEndTimeCode(frames - 1)
    strip = _quad(stage, "/Strip", [(0, 0, 0)] * 6, counts=(4, 4),
                  indices=(0, 1, 4, 3, 1, 2, 5, 4))
    for t in range(frames):
        strip.GetPointsAttr().Set([Gf.Vec3f(-1, -1, 0), Gf.Vec3f(0, -1, 0.1 * t),
                                   Gf.Vec3f(1, -1, 0), Gf.Vec3f(-1, 1, 0),
                                   Gf.Vec3f(0, 1, 0.1 * t), Gf.Vec3f(1, 1, 0)], t)
    st = UsdGeom.PrimvarsAPI(strip).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray,
                                                  UsdGeom.Tokens.faceVarying)
    # Each quad maps the whole image: the shared edge has two uv (a seam).
    st.Set([(0, 0), (1, 0), (1, 1), (0, 1)])
    st.SetIndices([0, 1, 2, 3, 0, 1, 2, 3])
    material = UsdShade.Material.Define(stage, "/Looks/Printed")
    surface = UsdShade.Shader.Define(stage, "/Looks/Printed/Surface")
    surface.CreateIdAttr("UsdPreviewSurface")
    image = UsdShade.Shader.Define(stage, "/Looks/Printed/Image")
    image.CreateIdAttr("UsdUVTexture")
    image.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(Sdf.AssetPath(str(texture)))
    reader = UsdShade.Shader.Define(stage, "/Looks/Printed/Reader")
    reader.CreateIdAttr("UsdPrimvarReader_float2")
    reader.CreateInput("varname", Sdf.ValueTypeNames.Token).Set("st")
    image.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(
        reader.ConnectableAPI(), "result")
    surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(
        image.ConnectableAPI(), "rgb")
    material.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
    _bind(strip, material)
    camera = UsdGeom.Camera.Define(stage, "/Cam")
    camera.AddTranslateOp().Set(Gf.Vec3d(0, 0, 4))
    dome = UsdLux.DomeLight.Define(stage, "/Sky")
    dome.CreateIntensityAttr(1.0)
    stage.GetRootLayer().Save()
    return path


def test23_uv_textures_map_the_image_upright_and_split_seams(tmp_path, capsys):
    texture = tmp_path / "print.exr"
    rows = np.zeros((8, 8, 3), dtype=np.float32)
    rows[:4, :, 0] = 1.0  # the image's top half red, its bottom half blue
    rows[4:, :, 2] = 1.0
    mi.Bitmap(rows).write(str(texture))
    path = write_textured(tmp_path / "printed.usda", texture)
    said, warn = lines()
    animation = UsdScene(path, warn=warn)
    assert not [line for line in said if "texture" in line], said
    strip = rendered_meshes(animation)["Strip"]
    assert strip.motion == "deforming" and len(strip.vertex_points) == 8  # 6 points, 2 split
    # Mitsuba's uv are (s, 1 - t): the first quad's corners (0,0) (1,0) (1,1) (0,1) in st.
    np.testing.assert_allclose(strip.texcoords[strip.faces[0]], [[0, 1], [1, 1], [1, 0]])
    scene = mi.load_dict(animation.scene_dict(resolution=(16, 16), spp=4))
    params = mi.traverse(scene)
    for i in range(2):
        scenes.apply_frame(scene, params, animation.frame(i))
        np.testing.assert_allclose(mitsuba_triangles(scene)["Strip"],
                                   pxr_triangles(path, Usd.TimeCode(i))["/Strip"], atol=1e-6)
    image = np.array(mi.render(scene, seed=0))
    top, bottom = image[3, 8], image[12, 8]
    assert top[0] > 5 * top[2] and bottom[2] > 5 * bottom[0], (top, bottom)
    folders = render_both(capsys, path, tmp_path / "out")
    assert_frames_agree(folders, range(2))
    digest = animation.source_digest()
    rows[0, 0] = 0.5
    mi.Bitmap(rows).write(str(texture))
    assert UsdScene(path, warn=warn).source_digest() != digest  # the texture is hashed


# ---- Prototypes and rigid motion as Mitsuba instances ----------------------------------


def _grounded_stage(path):
    """A new Y-up stage in metres, time codes 0..2, with an 8 m ground."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetStartTimeCode(0)
    stage.SetEndTimeCode(2)
    _quad(stage, "/Ground", [(-4, 0, -4), (4, 0, -4), (4, 0, 4), (-4, 0, 4)],
          indices=(0, 3, 2, 1))
    return stage


def _box(stage, path, half):
    """A closed box mesh of six quads, ``2 half.x`` by ``half.y`` (from y = 0) by
    ``2 half.z``."""
    hx, hy, hz = half
    corners = [(x, y, z) for x in (-hx, hx) for y in (0, hy) for z in (-hz, hz)]
    quads = (0, 1, 3, 2, 4, 6, 7, 5, 0, 4, 5, 1, 2, 3, 7, 6, 0, 2, 6, 4, 1, 5, 7, 3)
    return _quad(stage, path, corners, counts=(4,) * 6, indices=quads)


def write_crowd(path):
    """A ground and eight instances of one box prototype (time codes 0..2): one turned
    and mirrored, one bound to another material on its instance prim (a second group),
    two moving by their time-sampled transforms; a 2048-triangle sheet moved by its
    parent's transform; a dome and a sun."""
    stage = _grounded_stage(path)
    stage.CreateClassPrim("/Prototypes")
    prototype = stage.DefinePrim("/Prototypes/Box", "Xform")
    _box(stage, "/Prototypes/Box/Geom", (0.3, 0.5, 0.2))
    red = _preview(stage, "/Looks/Red", diffuseColor=(0.8, 0.1, 0.1))
    for k in range(8):
        instance = UsdGeom.Xform.Define(stage, f"/Crowd/Box_{k}")
        move = instance.AddTranslateOp()
        turn = instance.AddRotateYOp()
        if k in (2, 6):  # moving
            for t in (0, 1, 2):
                move.Set(Gf.Vec3d(-3 + 0.8 * k + 0.2 * t, 0.0, 0.3 * t), t)
                turn.Set(25.0 * t + 10 * k, t)
        else:
            move.Set(Gf.Vec3d(-3 + 0.8 * k, 0.0, -0.5 * (k % 2)))
            turn.Set(15.0 * k)
        if k == 3:
            instance.AddScaleOp().Set(Gf.Vec3f(-1.0, 1.2, 0.8))  # mirrored
        instance.GetPrim().GetReferences().AddInternalReference(prototype.GetPath())
        instance.GetPrim().SetInstanceable(True)
        if k == 5:
            _bind(instance, red)
    # A rigid mesh large enough to be an instance (RIGID_INSTANCE_TRIANGLES), not a proxy
    flyer = UsdGeom.Xform.Define(stage, "/Flyer")
    lift = flyer.AddTranslateOp()
    for t in (0, 1, 2):
        lift.Set(Gf.Vec3d(0.2 * t, 1.2 + 0.1 * t, -1.0), t)
    flyer.AddRotateXOp().Set(70.0)
    n = 32
    grid = [(x / n - 0.5, 0.0, z / n - 0.5) for z in range(n + 1) for x in range(n + 1)]
    cells = [(z * (n + 1) + x, z * (n + 1) + x + 1, (z + 1) * (n + 1) + x + 1, (z + 1) * (n + 1) + x)
             for z in range(n) for x in range(n)]
    _quad(stage, "/Flyer/Sheet", grid, counts=(4,) * len(cells),
          indices=[i for cell in cells for i in cell], double_sided=True)
    camera = UsdGeom.Camera.Define(stage, "/Cam")
    camera.AddTranslateOp().Set(Gf.Vec3d(0, 2.5, 7))
    camera.AddRotateXOp().Set(-15.0)
    UsdLux.DomeLight.Define(stage, "/Sky").CreateIntensityAttr(0.6)
    sun = UsdLux.DistantLight.Define(stage, "/Sun")
    sun.CreateIntensityAttr(2.0)
    sun.AddRotateXOp().Set(-60.0)
    stage.GetRootLayer().Save()
    return path


def test24_prototypes_and_rigid_motion_are_instances_of_shared_groups(tmp_path):
    """Eight proxies of one prototype: two shape groups (the red binding outside the
    prototype makes the second), each instance where pxr puts its mesh frame by frame
    (turned, mirrored, moving); the frames move only the two moving instances'
    transforms; ``instancing=False`` gives the same triangles as world-space meshes."""
    path = write_crowd(tmp_path / "crowd.usda")
    animation = UsdScene(path, warn=lambda line: None)
    groups = animation.instance_groups()
    assert len(groups) == 9 and len(set(groups.values())) == 3
    assert groups["Crowd_Box_5_Geom"] != groups["Crowd_Box_4_Geom"] == groups["Crowd_Box_3_Geom"]
    assert animation.animated_ids() == ["Crowd_Box_2_Geom", "Crowd_Box_6_Geom", "Flyer_Sheet"]
    assert animation.triangle_counts()["Crowd_Box_0_Geom"] == 12
    assert animation.triangle_counts()["Flyer_Sheet"] == 2048
    flat = UsdScene(path, warn=lambda line: None, instancing=False)
    assert flat.instance_groups() == {} and flat.motions() == animation.motions()
    scene = mi.load_dict(animation.scene_dict(resolution=(8, 8), spp=1))
    params = mi.traverse(scene)
    paths = animation.prim_paths()
    for i in range(animation.frame_count):
        frame = animation.frame(i)
        assert set(frame) == set(animation.animated_ids())
        assert all(g.to_world is not None and g.positions is None for g in frame.values())
        scenes.apply_frame(scene, params, frame)
        expected = pxr_triangles(path, Usd.TimeCode(i))
        ours = mitsuba_triangles(scene, groups)
        flat_triangles = flat.world_triangles(i)
        for shape_id, prim in paths.items():
            np.testing.assert_allclose(ours[shape_id], expected[prim], atol=1e-5,
                                       err_msg=f"{shape_id} at frame {i}")
            np.testing.assert_allclose(animation.world_triangles(i)[shape_id],
                                       expected[prim], atol=1e-9)
            # (the world-space copy of the mirrored box has its corners reversed)
            np.testing.assert_allclose(np.sort(flat_triangles[shape_id], axis=1),
                                       np.sort(expected[prim], axis=1), atol=1e-9)


def test25_an_instanced_stage_renders_as_native_rebuilding_only_the_top_level(tmp_path):
    """Frame by frame, hlbvh's images of the instanced crowd equal native's (and the
    world-space copies' in the mean); each frame refits or rebuilds the top level
    alone."""
    from hlbvh.render.frame import FrameRenderer
    from hlbvh.render.settings import RenderSettings
    path = write_crowd(tmp_path / "crowd.usda")
    settings = dict(resolution=(32, 24), spp=4, max_depth=3)
    renderers = {
        "hlbvh": FrameRenderer(UsdScene(path, warn=lambda line: None),  # our top level
                               RenderSettings(accel="hlbvh", moving_accel="hlbvh",
                                              **settings)),
        "native": FrameRenderer(UsdScene(path, warn=lambda line: None),
                                RenderSettings(accel="native", **settings)),
        "flat": FrameRenderer(UsdScene(path, warn=lambda line: None, instancing=False),
                              RenderSettings(accel="hlbvh", **settings))}
    for i in range(3):
        images_ = {name: np.array(r.render(i)[0]) for name, r in renderers.items()}
        assert images_["hlbvh"].mean() > 0.01
        assert_close_to_native(images_["hlbvh"], images_["native"])
        # The world-space copies are the same surfaces, but the mirrored copy's reversed
        # corners turn its shading frame's tangents, so a BSDF sample of the same random
        # numbers leaves in another direction: equal in the mean, not pixel for pixel.
        assert abs(images_["hlbvh"].mean() - images_["flat"].mean()) <= \
            0.02 * images_["flat"].mean()
        update = renderers["hlbvh"].integrator.accel(renderers["hlbvh"].scene).last_update
        assert update["groups"]["dynamic"]["triangles"] == 0
        assert update["groups"]["static"]["decision"] == ("build" if i == 0 else "kept")
        assert update["groups"]["instances"]["instances"] == 3
        if i:
            assert update["groups"]["instances"]["decision"] in ("refit", "rebuild")


def test26_a_prop_scaled_to_nothing_stays_a_world_space_mesh(tmp_path):
    """An animation that hides a prop by scaling it to 0 (and a proxy placed at scale
    0): an instance's transform must be invertible, so these stay world-space meshes,
    whose triangles collapse, and every frame renders."""
    from hlbvh.render.frame import FrameRenderer
    from hlbvh.render.settings import RenderSettings
    path = write_crowd(tmp_path / "crowd.usda")
    stage = Usd.Stage.Open(str(path))
    hide = UsdGeom.Xformable(stage.GetPrimAtPath("/Flyer")).AddScaleOp(opSuffix="hide")
    for t, scale in ((0, 1.0), (1, 0.0), (2, 1.0)):
        hide.Set(Gf.Vec3f(scale, scale, scale), t)
    UsdGeom.Xformable(stage.GetPrimAtPath("/Crowd/Box_7")).AddScaleOp(opSuffix="hide").Set(
        Gf.Vec3f(0.0, 1.0, 1.0))
    stage.GetRootLayer().Save()
    animation = UsdScene(path, warn=lambda line: None)
    groups = animation.instance_groups()
    assert "Flyer_Sheet" not in groups and "Crowd_Box_7_Geom" not in groups
    assert len(groups) == 7 and animation.motions()["Flyer_Sheet"] == "rigid"
    collapsed = animation.world_triangles(1)["Flyer_Sheet"].reshape(-1, 3)
    assert np.ptp(collapsed, axis=0).max() < 1e-9  # every corner at the prop's origin
    renderer = FrameRenderer(animation, RenderSettings(resolution=(16, 12), spp=1,
                                                       accel="hlbvh"))
    for i in range(animation.frame_count):
        image, _ = renderer.render(i)
        assert np.isfinite(np.array(image)).all()


def test27_stage_options_on_the_command_line(tmp_path, capsys, monkeypatch):
    """SCENE ``stage.usda:instancing=false`` renders the world-space model and is on
    record (a resume with another model is refused, as for another stage); a cluster's
    spec carries it; an unknown option or value is one line."""
    path = write_crowd(tmp_path / "crowd.usda")
    flat = f"{path}:instancing=false"
    animation, source, _ = open_animation(SceneSpec(flat, frames="0:1"))
    assert animation.instance_groups() == {} and source["scene"] == f"{path.resolve()}:instancing=false"
    assert open_animation(SceneSpec(str(path), frames="0:1"))[0].instance_groups()
    spec = SceneSpec.of(flat, None, None, range(0, 1)).absolute()
    assert spec.scene == source["scene"]
    status, _, err = run_cli(capsys, "render", flat, "--frames", "0:1", "--out",
                             tmp_path / "out", *TINY)
    assert status == 0, err
    document, _ = read_stats(tmp_path / "out")
    assert document["settings"]["scene"].endswith(":instancing=false")
    status, _, err = run_cli(capsys, "render", path, "--frames", "0:1", "--out",
                             tmp_path / "out", *TINY)
    assert status == 2 and len(err) == 1, err
    for bad, said in ((f"{path}:instance=false", "'instance=false' is not an option"),
                      (f"{path}:instancing=maybe", "expected true or false")):
        status, _, err = run_cli(capsys, "render", bad, "--frames", "0:1", "--out",
                                 tmp_path / "bad", *TINY)
        assert status == 2 and len(err) == 1 and said in err[0], err


def write_points(path):
    """A PointInstancer (time codes 0..2) of two prototypes: a box with its own
    translate, and a pair of quads in an Xform; six points turned, scaled and moving,
    one invisible, one scaled to nothing at the second frame."""
    stage = _grounded_stage(path)
    base = UsdGeom.Xform.Define(stage, "/Field")
    base.AddTranslateOp().Set(Gf.Vec3d(0.0, 0.2, -0.5))
    instancer = UsdGeom.PointInstancer.Define(stage, "/Field/Rocks")
    box = UsdGeom.Xform.Define(stage, "/Field/Rocks/Protos/Box")
    box.AddTranslateOp().Set(Gf.Vec3d(0.0, 0.1, 0.0))
    _box(stage, "/Field/Rocks/Protos/Box/Geom", (0.2, 0.3, 0.1))
    UsdGeom.Xform.Define(stage, "/Field/Rocks/Protos/Pair")
    _quad(stage, "/Field/Rocks/Protos/Pair/A", [(0, 0, 0), (0.3, 0, 0), (0.3, 0.3, 0), (0, 0.3, 0)],
          double_sided=True)
    side = _quad(stage, "/Field/Rocks/Protos/Pair/B",
                 [(0, 0, 0), (0, 0, 0.3), (0, 0.3, 0.3), (0, 0.3, 0)], double_sided=True)
    UsdGeom.Xformable(side).AddTranslateOp().Set(Gf.Vec3d(0.3, 0.0, 0.0))
    instancer.CreatePrototypesRel().SetTargets(["/Field/Rocks/Protos/Box",
                                                "/Field/Rocks/Protos/Pair"])
    instancer.CreateProtoIndicesAttr([0, 1, 0, 1, 0, 1])
    for t in (0, 1, 2):
        instancer.CreatePositionsAttr().Set(
            [Gf.Vec3f(-2.0 + 0.8 * k + 0.1 * t, 0.0, 0.2 * k - 0.05 * t) for k in range(6)], t)
        instancer.CreateOrientationsAttr().Set(
            [Gf.Quath(Gf.Rotation(Gf.Vec3d(0, 1, 0), 30.0 * k + 20.0 * t).GetQuat())
             for k in range(6)], t)
        instancer.CreateScalesAttr().Set(
            [Gf.Vec3f(0.0 if (k == 4 and t == 1) else 1.0 + 0.2 * k) for k in range(6)], t)
    instancer.CreateInvisibleIdsAttr([2])
    camera = UsdGeom.Camera.Define(stage, "/Cam")
    camera.AddTranslateOp().Set(Gf.Vec3d(0, 2.0, 6))
    camera.AddRotateXOp().Set(-15.0)
    UsdLux.DomeLight.Define(stage, "/Sky").CreateIntensityAttr(0.7)
    stage.GetRootLayer().Save()
    return path


def _point_triangles(path, time):
    """Each rendered point's prototype triangles in world space, by (point, mesh path),
    composed here from the instancer's attributes: parents, position, orientation,
    scale, the prototype root's own transform, the mesh's inside it."""
    stage = Usd.Stage.Open(str(path))
    instancer = UsdGeom.PointInstancer(stage.GetPrimAtPath("/Field/Rocks"))
    world = np.array(instancer.ComputeLocalToWorldTransform(time)).T
    targets = instancer.GetPrototypesRel().GetTargets()
    result = {}
    for k, (index, p, q, s) in enumerate(zip(
            instancer.GetProtoIndicesAttr().Get(time), instancer.GetPositionsAttr().Get(time),
            instancer.GetOrientationsAttr().Get(time), instancer.GetScalesAttr().Get(time))):
        if index >= len(targets):
            continue
        point = np.eye(4)
        point[:3, :3] = np.array(Gf.Matrix3d(Gf.Rotation(Gf.Quatd(q)))).T * np.array(s)
        point[:3, 3] = p
        root = stage.GetPrimAtPath(targets[index])
        root_world = np.array(UsdGeom.Xformable(root).ComputeLocalToWorldTransform(time)).T
        local = np.array(UsdGeom.Xformable(root).GetLocalTransformation(time)).T
        for prim in Usd.PrimRange(root):
            if prim.IsA(UsdGeom.Mesh):
                mesh = UsdGeom.Mesh(prim)
                inside = np.linalg.inv(root_world) @ np.array(
                    UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(time)).T
                m = world @ point @ local @ inside
                v = np.array(mesh.GetPointsAttr().Get(time), np.float64) @ m[:3, :3].T + m[:3, 3]
                faces = np.array(mesh.GetFaceVertexIndicesAttr().Get(time)).reshape(-1, 4)
                result[(k, str(prim.GetPath()))] = np.concatenate(
                    [v[faces[:, [0, 1, 2]]], v[faces[:, [0, 2, 3]]]])
    return result


def test28_a_point_instancer_renders_its_points_as_instances(tmp_path):
    """Each visible point is an instance of its prototype's groups (the pair's two
    meshes two instances), where the instancer's attributes put it frame by frame; the
    hidden and vanishing points are left out, said once; the frames move the
    points' transforms only, and hlbvh's images equal native's."""
    from hlbvh.render.frame import FrameRenderer
    from hlbvh.render.settings import RenderSettings
    path = write_points(tmp_path / "points.usda")
    said, warn = lines()
    animation = UsdScene(path, warn=warn)
    groups = animation.instance_groups()
    assert len(groups) == 7 and len(set(groups.values())) == 3  # points 0, 1, 3, 5 (pairs x2)
    assert sum("2 of its 6 points are not rendered" in line for line in said) == 1
    assert set(animation.animated_ids()) == set(groups)
    assert animation.static_ids() == ["Ground"]  # the prototypes render only as points
    for i in range(animation.frame_count):
        expected = _point_triangles(path, Usd.TimeCode(i))
        ours = animation.world_triangles(i)
        for k, mesh in ((0, "Box/Geom"), (1, "Pair/A"), (1, "Pair/B"), (5, "Pair/B")):
            key = (f"Field_Rocks_{k}" if mesh == "Box/Geom"
                   else f"Field_Rocks_{k}_{0 if mesh.endswith('A') else 1}")
            got = ours[key]
            want = expected[(k, f"/Field/Rocks/Protos/{mesh}")]
            # (orientations are half-precision quaternions, not of unit length: pxr and
            # this composition normalise them differently, 3e-4 apart at most here)
            np.testing.assert_allclose(np.sort(got.reshape(-1, 3), axis=0),
                                       np.sort(want.reshape(-1, 3), axis=0), atol=1e-3,
                                       err_msg=f"point {k} {mesh} at frame {i}")
    settings = dict(resolution=(32, 24), spp=4, max_depth=3)
    renderers = {accel: FrameRenderer(UsdScene(path, warn=lambda line: None),  # our top level
                                      RenderSettings(accel=accel, **settings,
                                                     moving_accel="hlbvh" if accel == "hlbvh"
                                                     else None))
                 for accel in ("hlbvh", "native")}
    for i in range(animation.frame_count):
        images_ = {a: np.array(r.render(i)[0]) for a, r in renderers.items()}
        assert images_["hlbvh"].mean() > 0.01
        assert_close_to_native(images_["hlbvh"], images_["native"])
        update = renderers["hlbvh"].integrator.accel(renderers["hlbvh"].scene).last_update
        assert update["groups"]["dynamic"]["triangles"] == 0
        assert update["groups"]["instances"]["instances"] == 7
