"""CorridorScene.first_hit: where rays from a camera meet the corridor."""

import numpy as np

from rsvo_ros.sim.synth import CAMERA_HEIGHT_M, CorridorScene, SequenceRenderer, SynthConfig


def test_rays_meet_the_floor_below_and_a_wall_to_each_side():
    renderer = SequenceRenderer(SynthConfig(frames=2, motion="walk", seed=3))
    _, R, p, *_ = renderer.frame_pose(0)
    scene: CorridorScene = renderer.scene
    down = np.array([[0.0, 1.0, 0.0]])  # y is down
    lam, which = scene.first_hit(p, down)
    assert which[0] == 2 and np.isclose(lam[0], scene.floor_y - p[1])
    assert np.isclose(scene.floor_y - p[1], CAMERA_HEIGHT_M, atol=0.1)  # the walk's bob
    sideways = np.asarray(R)[:, 0][None, :] * np.array([[1.0, 0.0, 1.0]])  # level, to the right
    lam, which = scene.first_hit(p, np.vstack([sideways, -sideways]))
    assert set(which.tolist()) == {0, 1}  # one wall each way
    cx, cz = scene.centre
    for k in range(2):
        X = p + lam[k] * (sideways[0] if k == 0 else -sideways[0])
        A, B = scene.wall_axes(int(which[k]))
        assert np.isclose(((X[0] - cx) / A) ** 2 + ((X[2] - cz) / B) ** 2, 1.0)
    zero = np.array([[0.0, 0.0, 0.0]])  # a zero direction meets nothing
    lam, which = scene.first_hit(p, zero)
    assert np.isinf(lam[0]) and which[0] == -1
