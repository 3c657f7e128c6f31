"""Visual modality: an RGB-D camera per world (Newton's ray-traced ``SensorCamera``) and coarse object
localisation from its depth image (table plane fit, segmentation, point cloud, centre and extents)."""

from d3grasp.vision.camera import CameraIntrinsics, RGBDCamera, look_at_pose
from d3grasp.vision.localisation import ObjectEstimate, localise_object

__all__ = ["CameraIntrinsics", "ObjectEstimate", "RGBDCamera", "localise_object", "look_at_pose"]
