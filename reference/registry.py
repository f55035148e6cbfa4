"""Registry of reference methods: id -> lazy "module:Class" (a `reference.method.Method`; one
module per method in `reference/methods/`). No method uses another, by its id or by its module:
what two methods share is a part of `reference/common` (Skyeyes' prior and the `sugar` row are
`common.sugar.SuGaRSplatting`; gvg's geometry and the `mvs` row `common.mvs_cloud.MVSCloud`)."""

from __future__ import annotations

METHODS: dict[str, str] = {
    "mean-frame": "reference.methods.mean_frame:MeanFrame",
    "mvs": "reference.methods.mvs:MVS",
    "nerf": "reference.methods.nerf:NeRF",
    "gaussians3d": "reference.methods.gaussians3d:Gaussians3D",
    "sugar": "reference.methods.sugar:SuGaR",
    "skyeyes": "reference.methods.skyeyes:Skyeyes",
    "skyeyes-no-vcm": "reference.methods.skyeyes:SkyeyesNoVCM",
    "skyeyes-geo": "reference.methods.skyeyes_geo:SkyeyesGeo",
    "skyeyes-geo-no-vcm": "reference.methods.skyeyes_geo:SkyeyesGeoNoVCM",
    "controlnet": "reference.methods.controlnet:ControlNetBaseline",
    "ip2p": "reference.methods.ip2p:InstructPix2Pix",
    "gvg": "reference.methods.gvg:GVG",
}


def get_method_class(name: str):
    """The Method class for `name`; a lookup miss lists the known ids."""
    from skyeyes_bench.registry import load_entry_point, lookup

    return load_entry_point(lookup(METHODS, name, "method"))
