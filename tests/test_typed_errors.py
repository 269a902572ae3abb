"""Errors that carry what they name as fields (the shape, the instance's index, the
accelerator to use instead), read by their callers instead of their text; still
ValueErrors with the same one-line message, and whole after a trip through pickle
(as a Dask worker's error reaches the client)."""

import pickle

import hlbvh
import mitsuba as mi
import numpy as np
import pytest

from hlbvh.accel.scene_geometry import ShapeError, scene_shapes
from hlbvh.errors import UserError
from hlbvh.kernels.instances import BadTransform, two_level
from hlbvh.render.frame import FrameRenderer
from hlbvh.render.settings import RenderSettings

from test_instances import GROUPS, _transforms
from test_static import _rigid_scene


def _instanced_scene():
    return mi.load_dict({
        "type": "scene",
        "group": {"type": "shapegroup", "s": {"type": "sphere"}},
        "copy": {"type": "instance", "shapegroup": {"type": "ref", "id": "group"}},
        "floor": {"type": "rectangle"},
    })


def test01_a_refused_shape_names_it_and_the_accelerator_to_use():
    with pytest.raises(ShapeError) as refused:
        scene_shapes(_instanced_scene().shapes(), "hlbvh")
    error = refused.value
    assert isinstance(error, ValueError)
    assert error.shape == "shape 'copy' (Instance)" and error.accel == "native"
    assert error.reason.startswith("shape 'copy' (Instance): with static='hlbvh'")
    assert str(error) == error.reason + " Use accel='native' for this scene."
    again = pickle.loads(pickle.dumps(error))
    assert (type(again), str(again), again.shape, again.reason, again.accel) == (
        ShapeError, str(error), error.shape, error.reason, error.accel)


def test02_bad_transform_carries_the_instance_and_what_is_wrong():
    bvhs = [hlbvh.build(mi.Float(v.ravel()), mi.UInt32(f.ravel())) for v, f in GROUPS]
    rows = _transforms(np.random.default_rng(1), 3)
    rows[2, :9] = np.diag([1.0, 1.0, 0.0]).ravel()
    with pytest.raises(BadTransform) as refused:
        two_level(bvhs, mi.UInt32([0, 1, 0]), mi.Float(rows.ravel()))
    error = refused.value
    assert (error.index, error.what) == (2, "singular (a scale of 0)")
    again = pickle.loads(pickle.dumps(error))
    assert (str(again), again.index, again.what) == (str(error), 2, error.what)


def test03_an_instance_with_a_singular_transform_is_named_by_the_accelerator():
    """The accelerator turns the kernel's instance position into the scene's shape."""
    scene = mi.load_dict(_rigid_scene())
    params = mi.traverse(scene)
    accel = hlbvh.SceneAccel(scene, moving=["inst_3"])
    params["inst_3.to_world"] = mi.Transform4f().scale([1.0, 0.0, 1.0])
    params.update()
    with pytest.raises(ShapeError) as refused:
        accel.update()
    error = refused.value
    assert error.shape == "shape 'inst_3' (Instance)" and error.accel is None
    assert str(error) == "shape 'inst_3' (Instance): its to_world is singular (a scale of 0)"


def test04_the_renderer_reads_the_reason_and_names_its_own_flag(monkeypatch):
    """``hlbvh render`` says ``--accel native`` where the accelerator says
    ``accel='native'``: the reason is read from the error's field."""
    def refuse(shapes, static):
        raise ShapeError("shape 'x' (Curve)", "shape 'x' (Curve): not traced.", "native")
    monkeypatch.setattr("hlbvh.render.frame.scene_shapes", refuse)
    with pytest.raises(UserError) as refused:
        FrameRenderer(hlbvh.scenes.get("cloth", triangles=200, frames=2),
                      RenderSettings(resolution=(8, 8), spp=1, accel="hlbvh"))
    assert str(refused.value) == ("shape 'x' (Curve): not traced. Render this scene with "
                                  "--accel native (Mitsuba's own accelerator).")
