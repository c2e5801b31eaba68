"""prt_torch.sh — the spherical-harmonics mathematics every other module leans on. No I/O.

Conventions: real SH, graphics convention (Ramamoorthi 2002 eq. 4.5, no Condon-Shortley
phase), flat index l(l+1)+m, ``bands`` n = n² coefficients. Coefficients are the *last* axis.
"""
from .basis import MAX_BANDS, band_of_coeffs, eval_sh, eval_zonal_basis, lm_of, num_coeffs, sh_index
from .quadrature import (
    fibonacci_sphere,
    gauss_hemisphere,
    gauss_sphere,
    latlong_grid,
    project,
    project_callable,
    reconstruct,
    stratified_sphere,
    stratified_square,
)
from .rotation import blocks_to_dense, random_rotations, rotate, rotation_blocks, rotation_matrix
from .zonal import (
    band_energy,
    band_factor,
    bands_for_energy,
    clamped_cosine,
    clamped_cosine_A,
    convolve,
    gauss_legendre,
    microfacet,
    phong,
    rotate_zonal,
    window,
    zonal_project,
)
from .hemisphere import (
    hemisphere_gram,
    hemisphere_projector,
    project_hemisphere,
    projection_error,
    redundancy_errors,
)

__all__ = [
    "MAX_BANDS",
    "band_of_coeffs",
    "eval_sh",
    "eval_zonal_basis",
    "lm_of",
    "num_coeffs",
    "sh_index",
    "fibonacci_sphere",
    "gauss_hemisphere",
    "gauss_sphere",
    "latlong_grid",
    "project",
    "project_callable",
    "reconstruct",
    "stratified_sphere",
    "stratified_square",
    "blocks_to_dense",
    "random_rotations",
    "rotate",
    "rotation_blocks",
    "rotation_matrix",
    "band_energy",
    "band_factor",
    "bands_for_energy",
    "clamped_cosine",
    "clamped_cosine_A",
    "convolve",
    "gauss_legendre",
    "microfacet",
    "phong",
    "rotate_zonal",
    "window",
    "zonal_project",
    "hemisphere_gram",
    "hemisphere_projector",
    "project_hemisphere",
    "projection_error",
    "redundancy_errors",
]
