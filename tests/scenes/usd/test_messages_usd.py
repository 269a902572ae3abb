"""USD stages whose frames or values go wrong mid-animation (issue 33, items 2, 7, 8, 9):
each frame renders the same image whichever frames came before it, the work follows the
frames asked for and not the stage's time range, and each bad value is one line naming
the stage, the prim and the frame."""

import numpy as np
import pytest

pxr = pytest.importorskip("pxr")

from pxr import Gf, Usd, UsdGeom, UsdLux  # noqa: E402

from cli_helpers import run_cli  # noqa: E402
from hlbvh.render import images  # noqa: E402
from hlbvh.render.frame import FrameRenderer  # noqa: E402
from hlbvh.render.settings import RenderSettings  # noqa: E402
from hlbvh.scenes import usd  # noqa: E402
from hlbvh.scenes.usd import UsdScene  # noqa: E402
from hlbvh.scenes.usd.instances import Placements  # noqa: E402

TINY = ["--resolution", "24", "--spp", "2", "--quiet"]


def _stage(path, end=3):
    """A Y-up stage in metres, time codes 0..``end``, a dome light and a camera at
    z = 4 looking down -Z."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetStartTimeCode(0)
    stage.SetEndTimeCode(end)
    UsdLux.DomeLight.Define(stage, "/Sky").CreateIntensityAttr(1.0)
    camera = UsdGeom.Camera.Define(stage, "/Cam")
    camera.AddTranslateOp().Set(Gf.Vec3d(0, 0, 4))
    return stage


def _mesh(stage, path, points, counts, indices):
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreatePointsAttr([Gf.Vec3f(*p) for p in points])
    mesh.CreateFaceVertexCountsAttr(list(counts))
    mesh.CreateFaceVertexIndicesAttr(list(indices))
    mesh.CreateSubdivisionSchemeAttr("none")
    return mesh


SQUARE = [(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)]  # facing +Z: the camera


def _normals(triangles):
    """Each triangle's unit geometric normal, from its winding."""
    n = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def _mitsuba_normals(renderer, shape_id):
    """The loaded Mitsuba mesh's triangles' normals, as the frame left them."""
    import mitsuba as mi
    params = mi.traverse(renderer.scene)
    points = np.array(params[f"{shape_id}.vertex_positions"]).reshape(-1, 3)
    faces = np.array(params[f"{shape_id}.faces"]).reshape(-1, 3)
    return _normals(points[faces].astype(np.float64))


# ---- Item 2: a world-space mesh's winding follows each frame's mirroring --------------


@pytest.mark.parametrize("instancing", [True, False])
def test_a_mirror_that_comes_and_goes_keeps_the_faces_facing_out(tmp_path, instancing):
    """A one-sided square under a parent mirrored in x at frames 0 and 2 and not at 1 and
    3 (a small rigid mesh: world space, with or without instancing): every frame's
    triangles face the camera, in pxr's triangles and in the loaded mesh, and every
    frame renders as bright as frame 0 (it rendered black at frames 1 and 3), in order
    or alone."""
    stage = _stage(tmp_path / "mirror.usda")
    scale = UsdGeom.Xform.Define(stage, "/Mirror").AddScaleOp()
    for t in range(4):
        scale.Set(Gf.Vec3f(-1 if t % 2 == 0 else 1, 1, 1), t)
    _mesh(stage, "/Mirror/Square", SQUARE, (4,), (0, 1, 2, 3))
    stage.GetRootLayer().Save()
    animation = UsdScene(tmp_path / "mirror.usda", warn=lambda line: None,
                         instancing=instancing)
    assert animation.instance_groups() == {}
    settings = RenderSettings(resolution=(16, 16), spp=4, accel="hlbvh")
    in_order = FrameRenderer(animation, settings)
    means = []
    for i in range(4):
        assert (_normals(animation.world_triangles(i)["Mirror_Square"])[:, 2] > 0.99).all()
        image, _ = in_order.render(i)
        assert (_mitsuba_normals(in_order, "Mirror_Square")[:, 2] > 0.99).all(), i
        means.append(float(np.array(image)[..., :3].mean()))
        alone, _ = FrameRenderer(animation, settings).render(i)
        assert np.array_equal(np.array(alone), np.array(image)), i
    assert min(means) > 0.45 and max(means) - min(means) < 0.03, means


# ---- Item 7: the work follows the frames asked for ------------------------------------


def _long_stage(path, end):
    """time codes 0..``end``: a rigid sheet of 2,048 triangles (an instance) whose
    parent's translation is sampled at 0, 1, 2, and a point instancer whose positions
    are sampled at 0, 1, 2."""
    stage = _stage(path, end=end)
    move = UsdGeom.Xform.Define(stage, "/Mover").AddTranslateOp()
    for t in (0, 1, 2):
        move.Set(Gf.Vec3d(0.1 * t, 0, 0), t)
    n = 33
    points = [(i / n - 0.5, j / n - 0.5, 0) for j in range(n) for i in range(n)]
    quads = [k for j in range(n - 1) for i in range(n - 1)
             for k in (j * n + i, j * n + i + 1, j * n + i + n + 1, j * n + i + n)]
    _mesh(stage, "/Mover/Sheet", points, [4] * (n - 1) ** 2, quads)
    instancer = UsdGeom.PointInstancer.Define(stage, "/Points")
    _mesh(stage, "/Points/Protos/Tri", [(0, 0, 0), (0.2, 0, 0), (0, 0.2, 0)], (3,), (0, 1, 2))
    instancer.CreatePrototypesRel().AddTarget("/Points/Protos/Tri")
    instancer.CreateProtoIndicesAttr([0, 0])
    positions = instancer.CreatePositionsAttr()
    for t in (0, 1, 2):
        positions.Set([Gf.Vec3f(1, 0.1 * t, 0), Gf.Vec3f(-1, 0, 0)], t)
    stage.GetRootLayer().Save()
    return path


def test_a_long_time_range_costs_what_its_samples_and_the_frames_asked_for_cost(
        tmp_path, monkeypatch):
    """endTimeCode 1e6 with a rigid instance of 2,048 triangles and a point instancer:
    loading the stage and taking frames 0..2 evaluates transforms at a handful of time
    codes (the samples, the first and last frames, the frames asked for), not once per
    frame of the range (a million XformCaches and point instancer evaluations, 3 GB)."""
    path = _long_stage(tmp_path / "long.usda", end=1e6)
    made, evaluated = [], []
    real_cache, real_points = UsdGeom.XformCache, Placements.points
    monkeypatch.setattr(UsdGeom, "XformCache",
                        lambda *a: made.append(a) or real_cache(*a))
    monkeypatch.setattr(Placements, "points",
                        lambda self, p, t, base=None: evaluated.append(t.GetValue())
                        or real_points(self, p, t, base))
    animation = UsdScene(path, warn=lambda line: None)
    assert animation.frame_count == 1_000_001
    assert set(animation.motions().values()) == {"rigid"}
    assert "Mover_Sheet" in animation.instance_groups()
    for i in range(3):
        animation.frame(i)
    assert len(made) <= 12, len(made)
    assert len(set(evaluated)) <= 5 and len(evaluated) <= 12, evaluated


# ---- Item 8: one outcome whichever way the frames are reached -------------------------


def _grid(n):
    return [(x / 4 - 0.5, y / 4 - 0.5, 0) for y in range(5) for x in range(5)][:25] + \
        [(9, 9, 9)] * (n - 25)


def _recounted_stage(path, counts):
    """A 5x5-point grid of 16 quads whose points attribute holds ``counts[t]`` points
    at time code t (the faces use the first 25; the rest are spares, far off)."""
    stage = _stage(path, end=len(counts) - 1)
    quads = [k for y in range(4) for x in range(4)
             for k in (5 * y + x, 5 * y + x + 1, 5 * y + x + 6, 5 * y + x + 5)]
    mesh = _mesh(stage, "/Grid", _grid(25), [4] * 16, quads)
    for t, n in enumerate(counts):
        points = [(x, y + 0.05 * t, z) for x, y, z in _grid(max(n, 25))][:n]
        mesh.GetPointsAttr().Set([Gf.Vec3f(*p) for p in points], t)
    stage.GetRootLayer().Save()
    return path


def test_a_point_count_that_returns_renders_the_same_fresh_or_resumed(tmp_path, capsys):
    """Points 25 -> 30 -> 30 -> 25: a fresh run of frames 0:4 renders frame 3 (it
    failed there: the mesh still held 30 vertices), and its frame 3 is the one a run
    of frame 3 alone renders."""
    path = _recounted_stage(tmp_path / "recount.usda", (25, 30, 30, 25))
    for name, frames in (("all", "0:4"), ("alone", "3:4")):
        status, _, err = run_cli(capsys, "render", path, "--frames", frames, "--out",
                                 tmp_path / name, *TINY)
        assert status == 0 and err == [], err
    both = [images.read_exr(tmp_path / name / "frame_0003.exr", ["R", "G", "B"])
            for name in ("all", "alone")]
    assert both[0].mean() > 0.1 and np.array_equal(*both)


def test_too_few_points_at_a_frame_names_the_stage_prim_and_frame(tmp_path, capsys):
    path = _recounted_stage(tmp_path / "short.usda", (25, 25, 20))
    status, _, err = run_cli(capsys, "render", path, "--frames", "0:3", "--out",
                             tmp_path / "out", *TINY)
    assert status == 2 and err == [
        f"hlbvh render: stage {str(path)!r}: mesh /Grid has 20 points at frame 2 (time code 2), "
        f"too few for its faces"], err


# ---- Item 9: values and USD's own diagnostics as one line -----------------------------


def _square_stage(path, bad: str):
    """A square under /Move whose translation is sampled at 0, 1, 2, with ``bad`` at
    time code 1: ``points`` (a NaN point), ``transform`` (a NaN translation),
    ``index`` (a face index -1)."""
    stage = _stage(path, end=2)
    move = UsdGeom.Xform.Define(stage, "/Move").AddTranslateOp()
    for t in (0, 1, 2):
        move.Set(Gf.Vec3d(float("nan") if bad == "transform" and t == 1 else 0.1 * t, 0, 0), t)
    mesh = _mesh(stage, "/Move/Square", SQUARE, (4,), (0, 1, 2, -1 if bad == "index" else 3))
    if bad == "points":
        for t in (0, 1, 2):
            corners = [(x, y, float("nan") if t == 1 and k == 2 else z)
                       for k, (x, y, z) in enumerate(SQUARE)]
            mesh.GetPointsAttr().Set([Gf.Vec3f(*p) for p in corners], t)
    stage.GetRootLayer().Save()
    return path


@pytest.mark.parametrize("bad, line", [
    ("points", "/Move/Square: its points at frame 1 (time code 1) are not finite "
               "(point 2 of 4)"),
    ("transform", "/Move/Square: its transform at frame 1 (time code 1) is not finite"),
    ("index", "mesh /Move/Square: faceVertexIndices holds -1: expected indices >= 0"),
])
def test_bad_values_name_the_stage_prim_and_frame(tmp_path, capsys, bad, line):
    path = _square_stage(tmp_path / f"{bad}.usda", bad)
    status, _, err = run_cli(capsys, "render", path, "--frames", "0:3", "--out",
                             tmp_path / "out", *TINY)
    assert status == 2 and err == [f"hlbvh render: stage {str(path)!r}: {line}"], err


@pytest.mark.parametrize("start, end, said", [
    (-1e300, 1e300, "startTimeCode -1e+300: expected a finite time code within +-2^52 "
                    "(frame i is at startTimeCode + i)"),
    (0, 1e12, "startTimeCode..endTimeCode 0..1e+12 holds more than 2^32 frames (a "
              "frame's seed is 32-bit)"),
])
def test_a_huge_time_range_is_one_short_line(tmp_path, capsys, start, end, said):
    path = tmp_path / "huge.usda"
    stage = _stage(path)
    _mesh(stage, "/Square", SQUARE, (4,), (0, 1, 2, 3))
    stage.SetStartTimeCode(start)
    stage.SetEndTimeCode(end)
    stage.GetRootLayer().Save()
    status, _, err = run_cli(capsys, "render", path, "--out", tmp_path / "out", *TINY)
    assert status == 2 and err == [f"hlbvh render: stage {str(path)!r}: {said}"], err
    assert len(err[0]) < 200


def test_usd_s_own_warnings_are_one_line_each_and_numpy_s_none(tmp_path, capfd):
    """A point instancer with 3 positions for 2 proto indices: USD prints a multi-part
    diagnostic of its own on stderr at every evaluation; it reaches the user once, as
    one ``hlbvh:`` line naming the stage, and nothing else reaches stderr (no numpy
    RuntimeWarning either)."""
    path = _long_stage(tmp_path / "odd.usda", end=2)
    stage = Usd.Stage.Open(str(path))
    UsdGeom.PointInstancer(stage.GetPrimAtPath("/Points")).GetPositionsAttr().Set(
        [Gf.Vec3f(0, 0, 0)] * 3, 1)
    stage.GetRootLayer().Save()
    animation = UsdScene(path)
    for i in range(3):
        animation.frame(i)
    err = [line for line in capfd.readouterr().err.splitlines() if line.strip()]
    said = [line for line in err if "USD says" in line]
    assert len(said) == 1 and said[0].startswith(f"hlbvh: stage {str(path)!r}: USD says: "
                                                 f"/Points -- found [3] positions"), err
    assert all(line.startswith("hlbvh: ") for line in err), err
    assert not any("Warning" in line for line in err), err


def test_a_stage_option_given_twice_is_refused(tmp_path, capsys):
    path = _square_stage(tmp_path / "shot.usda", "none")
    scene = f"{path}:instancing=false,instancing=true"
    status, _, err = run_cli(capsys, "render", scene, "--out", tmp_path / "out", *TINY)
    assert status == 2 and err == [
        f"hlbvh render: scene {scene!r}: instancing is given twice; give it once"], err


def test_the_sample_times_a_check_visits(tmp_path):
    """:func:`usd._sample_times`: the first and last time codes and the samples between,
    whatever the range's length."""
    stage = Usd.Stage.CreateInMemory()
    attribute = UsdGeom.Xform.Define(stage, "/X").AddTranslateOp().GetAttr()
    for t in (-5, 0, 2.5, 7, 1e6 + 1):
        attribute.Set(Gf.Vec3d(t, 0, 0), t)
    assert usd._sample_times([attribute], 0.0, 1e6) == [0.0, 2.5, 7.0, 1e6]


# ---- Issue 32 item 7: one line per missing file, the instancer's own reason -----------


def _referencing(path, count, with_mesh):
    """``count`` prims referencing one missing layer; with ``with_mesh`` a square too."""
    stage = _stage(path, end=0)
    for k in range(count):
        stage.DefinePrim(f"/Set_{k:02d}").GetReferences().AddReference("./missing.usda")
    if with_mesh:
        _mesh(stage, "/Square", SQUARE, (4,), (0, 1, 2, 3))
    stage.GetRootLayer().Save()
    return path


def test_many_references_to_one_missing_file_are_one_line_in_every_command(tmp_path,
                                                                         capsys):
    path = _referencing(tmp_path / "refs.usda", 30, with_mesh=False)
    said = {}
    for command in ("render", "compare"):
        status, _, err = run_cli(capsys, command, path, "--out", tmp_path / command, *TINY)
        assert status == 2 and len(err) == 1, err
        said[command] = err[0].removeprefix(f"hlbvh {command}: ")
    assert said["render"] == said["compare"]
    missing = f"@{tmp_path / 'missing.usda'}@"
    assert said["render"] == (
        f"stage {str(path)!r}: nothing renderable (no visible UsdGeom.Mesh of purpose default "
        f"or render); references or payloads that do not resolve: /Set_00 and 29 other "
        f"prims (Could not open asset {missing})"), said
    lines = []
    lit = _referencing(tmp_path / "lit.usda", 30, with_mesh=True)
    UsdScene(lit, warn=lines.append)
    assert [line for line in lines if "resolve" in line] == [
        f"stage {str(lit)!r}: /Set_00 and 29 other prims: a reference or payload does not "
        f"resolve (Could not open asset {missing}); what it would bring is not rendered"]


def test_a_point_instancer_alone_gives_its_own_reason(tmp_path, capsys):
    path = _long_stage(tmp_path / "points.usda", end=2)
    stage = Usd.Stage.Open(str(path))
    stage.RemovePrim("/Mover")
    UsdGeom.PointInstancer(stage.GetPrimAtPath("/Points")).GetProtoIndicesAttr().Set(
        [0, 0, 0], 2)
    UsdGeom.PointInstancer(stage.GetPrimAtPath("/Points")).GetPositionsAttr().Set(
        [Gf.Vec3f(0, 0, 0)] * 3, 2)
    stage.GetRootLayer().Save()
    status, _, err = run_cli(capsys, "render", path, "--out", tmp_path / "out", *TINY)
    assert status == 2 and err == [
        f"hlbvh render: stage {str(path)!r}: nothing renderable (no visible UsdGeom.Mesh of "
        f"purpose default or render); /Points: a PointInstancer whose number of points "
        f"changes over time is not supported; it is not rendered"], err
