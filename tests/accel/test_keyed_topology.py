"""A keyed mesh group's tree quality over the shutter (issue: the keyed tree's expected
SAH over time, and the topology rebuilt when it degrades): what the accelerator's update
reports for a moving mesh with motion keys, and which topology its policy keeps."""

import hlbvh
import mitsuba as mi
import numpy as np
import pytest

from test_keyed import _swap_keys  # noqa: E402

T = mi.ScalarTransform4f


def _scene(vertices, faces, update="auto", builder="hlbvh"):
    mesh = mi.Mesh("mover", len(vertices), len(faces))
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(vertices.ravel())
    params["faces"] = mi.UInt32(faces.ravel())
    params.update()
    return mi.load_dict({
        "type": "scene",
        "integrator": {"type": "hlbvh_path", "max_depth": 2, "update": update,
                       "builder": builder, "moving": "mover"},
        "sensor": {"type": "perspective", "to_world": T().look_at([0.5, 0.5, 3], [0.5, 0.5, 0],
                                                                 [0, 1, 0]),
                   "shutter_open": 0.0, "shutter_close": 1.0,
                   "film": {"type": "hdrfilm", "width": 16, "height": 16},
                   "sampler": {"type": "independent", "sample_count": 1}},
        "mover": mesh, "light": {"type": "constant"}})


@pytest.mark.parametrize("update, builder, topology", [
    ("auto", "sah", "union"),  # degraded past refit_tolerance: the better of the two
    ("rebuild", "sah", "mid"),  # other policies: the mid-shutter tree
    ("auto", "hlbvh", "mid"),  # a Morton builder's union topology is its mid-shutter one
])
def test01_a_scrambling_motion_reports_its_sah_over_the_shutter_and_its_topology(
        update, builder, topology):
    vertices, moved, faces = _swap_keys()
    scene = _scene(vertices, faces, update, builder)
    mover = next(s for s in scene.shapes() if s.id() == "mover")
    hlbvh.set_motion_keys(mover, [mi.Float(vertices.ravel()), mi.Float(moved.ravel())],
                          (0.0, 1.0))
    mi.render(scene)
    accel = scene.integrator().scene_accel
    group = accel.dynamic
    assert group.keyed.topology == topology
    last = accel.last_update["groups"]["dynamic"]
    assert last["sah_cost"] == pytest.approx(group.keyed.sah)
    assert last["drift"] == pytest.approx(group.keyed.sah / group.keyed.still_sah)
    assert last["drift"] > 1.5
    assert accel.last_update["sah_cost"] == pytest.approx(group.keyed.sah)


def test02_equal_keys_report_the_still_sah():
    vertices, _, faces = _swap_keys()
    scene = _scene(vertices, faces)
    mover = next(s for s in scene.shapes() if s.id() == "mover")
    hlbvh.set_motion_keys(mover, [mi.Float(vertices.ravel())] * 2, (0.0, 1.0))
    mi.render(scene)
    accel = scene.integrator().scene_accel
    assert accel.dynamic.keyed.topology == "mid"
    last = accel.last_update["groups"]["dynamic"]
    assert last["drift"] == pytest.approx(1.0)
    assert last["sah_cost"] == pytest.approx(float(accel.dynamic.bvh.stats.sah_cost))
