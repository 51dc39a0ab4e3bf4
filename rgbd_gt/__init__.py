"""rgbd-gt: ground-truth RGB-D data from a terrestrial laser scan and photos.

The workflow's steps are the Python API as well as the commands' (docs/api.md):

    import rgbd_gt
    photo = rgbd_gt.open_photo("photo.png", "camera.yaml")
    inputs = rgbd_gt.load_inputs("scan.e57", "photo.png", "camera.yaml", "init.yaml")
    refined = rgbd_gt.refine_step(inputs, rgbd_gt.refine_config(), "init.yaml")

Names are loaded when first used, so that `import rgbd_gt` (and `rgbd-gt --help`) stays quick.
"""

from importlib import import_module
from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("rgbd-gt")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0.0.0+unknown"

_API = {
    "rgbd_gt.steps": ("open_photo", "load_inputs", "refine_config", "refine_step", "bundle_step", "depth_step", "write_depth",
                      "qa_step", "overlay_step", "Photo", "Refined", "Bundled", "QA", "Overlay"),
    "rgbd_gt.io.bundle_file": ("read_bundle",),
    "rgbd_gt.export.dataset": ("export_run", "products", "stereo_products", "DepthProducts", "StereoProducts", "Exported"),
    "rgbd_gt.export.source": ("read_run", "Shot", "Source"),
    "rgbd_gt.export.stereo": ("pinhole", "rectify"),
    "rgbd_gt.export.uncertainty": ("pixel_sigma",),
    "rgbd_gt.export.report": ("write_report",),
    "rgbd_gt.align.bundle": ("Bundle", "BundlePhoto"),
    "rgbd_gt.align.refine": ("RefineInputs",),
    "rgbd_gt.render.renders": ("Renders",),
    "rgbd_gt.prepared": ("prepare_scan", "scan_in_view", "view_and_around"),
    "rgbd_gt.camera": ("Camera",),
    "rgbd_gt.scan": ("Scan", "scan_colors"),
    "rgbd_gt.io": ("load_scan", "read_camera", "read_pose", "write_pose"),
    "rgbd_gt.io.image": ("read_image",),
    "rgbd_gt.errors": ("InputError",),
}
_WHERE = {name: module for module, names in _API.items() for name in names}
__all__ = sorted(_WHERE)


def __getattr__(name: str):
    if name not in _WHERE:
        raise AttributeError(f"module 'rgbd_gt' has no attribute {name!r}")
    return getattr(import_module(_WHERE[name]), name)
