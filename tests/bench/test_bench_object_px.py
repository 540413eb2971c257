"""bench/object_px.py: SfM's cameras against the true ones, in pixels on the object, after the best similarity."""
import numpy as np
import pytest

from bench.object_px import object_px
from dvr.cameras import project_points


def _model():
    import pycolmap

    pycolmap.set_random_seed(0)
    o = pycolmap.SyntheticDatasetOptions()
    o.num_rigs, o.num_frames_per_rig, o.num_points3D = 1, 8, 200
    o.camera_model_id = pycolmap.CameraModelId.PINHOLE
    o.camera_params = [1000.0, 1000.0, 400.0, 300.0]
    o.sensor_from_rig_translation_stddev = o.sensor_from_rig_rotation_stddev = 0.0
    return pycolmap.synthesize_dataset(o)


def _truth(rec):
    points = np.stack([p.xyz for p in rec.points3D.values()])
    pixels, centres = {}, {}
    for i in rec.reg_image_ids():
        im = rec.image(i)
        M = np.asarray(im.cam_from_world().matrix())
        name = im.name.rsplit(".", 1)[0]
        pixels[name] = project_points(rec.camera(im.camera_id).calibration_matrix() @ M, points)[0]
        centres[name] = -M[:, :3].T @ M[:, 3]
    return points, pixels, centres


def test_true_cameras_in_another_frame_put_the_object_where_it_is():
    import pycolmap

    rec = _model()
    points, pixels, centres = _truth(rec)
    assert max(object_px(rec, pixels, centres, points).values()) < 1e-6
    moved = pycolmap.Reconstruction(rec)  # a similarity of the whole model: the cameras see the object the same
    moved.transform(pycolmap.Sim3d(1.7, pycolmap.Rotation3d(np.array([0.1, -0.2, 0.3])), np.array([0.5, 2.0, -1.0])))
    assert max(object_px(moved, pixels, centres, points).values()) < 1e-4


def test_one_camera_turned_is_the_view_off_by_its_angle_times_the_focal_length():
    import pycolmap

    rec = _model()
    points, pixels, centres = _truth(rec)
    turned = pycolmap.Reconstruction(rec)
    i = sorted(turned.reg_image_ids())[3]
    pose = turned.image(i).cam_from_world()
    angle = np.radians(0.05)
    turn = pycolmap.Rigid3d(pycolmap.Rotation3d(np.array([0.0, angle, 0.0])), np.zeros(3))  # about the camera centre
    turned.frame(turned.image(i).frame_id).set_cam_from_world(turned.image(i).camera_id, turn * pose)
    px = object_px(turned, pixels, centres, points)
    name = turned.image(i).name.rsplit(".", 1)[0]
    assert px[name] == pytest.approx(1000.0 * angle, rel=0.25)  # ≈ 0.87 px; the similarity spreads a little
    assert max(v for n, v in px.items() if n != name) < 0.3 * px[name]


def test_a_camera_moved_along_its_axis_does_not_move_the_object_in_the_other_views():
    """A camera centre moved along its optical axis barely changes that view's picture of the object, but it moves
    the Sim(3) of the camera centres; the similarity fitted to the object's projections keeps the other views right."""
    import pycolmap

    rec = _model()
    points, pixels, centres = _truth(rec)
    moved = pycolmap.Reconstruction(rec)
    i = sorted(moved.reg_image_ids())[2]
    pose = moved.image(i).cam_from_world()
    dist = np.linalg.norm(centres[moved.image(i).name.rsplit(".", 1)[0]] - points.mean(0))
    back = pycolmap.Rigid3d(pycolmap.Rotation3d(np.zeros(3)), np.array([0.0, 0.0, 0.05 * dist]))  # 5 % further away
    moved.frame(moved.image(i).frame_id).set_cam_from_world(moved.image(i).camera_id, back * pose)
    px = object_px(moved, pixels, centres, points)
    name = moved.image(i).name.rsplit(".", 1)[0]
    print(px)
    assert max(v for n, v in px.items() if n != name) < 0.2 * px[name]
