"""prt_torch.lighting — HDR environment maps in every common layout, SH projection, analytic
lights, irradiance (Ramamoorthi 2002 ch. 4). See docs/lighting.md for the world frame and the
pixel -> direction mapping of each layout.

Light vectors are ``[C, n²]`` float64 (C = 3 for RGB), coefficients last.
"""
from .layouts import (
    FACE_NAMES,
    LAYOUTS,
    detect_layout,
    dir_to_pixel,
    euler_matrix,
    layout_shape,
    pixel_directions,
    pixel_to_dir,
    resolve_rotation,
    solid_angles,
    up_rotation,
    valid_mask,
)
from .imageio import read_image, write_image
from .environment import Environment, load_environment, project_images, render_sh, window_factors
from .analytic import cap, cap_zonal, constant, directional, hemisphere, sky_gradient
from .irradiance import (
    irradiance,
    irradiance_coeffs,
    irradiance_constants,
    irradiance_map,
    irradiance_matrix,
    irradiance_polynomial,
    irradiance_quadratic,
)
from .builtin import builtin_environment, list_builtin_environments
from .spec import load_light, parse_light_spec
from .prefilter import PrefilteredEnvironment, prefilter_environment, spherical_gaussian

__all__ = [
    "LAYOUTS", "FACE_NAMES", "detect_layout", "layout_shape", "pixel_to_dir", "dir_to_pixel", "pixel_directions",
    "solid_angles", "valid_mask", "up_rotation", "euler_matrix", "resolve_rotation",
    "read_image", "write_image",
    "Environment", "load_environment", "render_sh", "project_images", "window_factors",
    "directional", "cap", "cap_zonal", "sky_gradient", "hemisphere", "constant",
    "irradiance", "irradiance_coeffs", "irradiance_constants", "irradiance_map", "irradiance_matrix",
    "irradiance_polynomial", "irradiance_quadratic",
    "builtin_environment", "list_builtin_environments", "load_light", "parse_light_spec",
    "PrefilteredEnvironment", "prefilter_environment", "spherical_gaussian",
]
