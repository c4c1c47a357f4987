from estimators import (
    circle_edges,
    circle_fit,
    clipped_noise,
    corners,
    edge_fit,
    edge_search,
    least_squares,
    lens_distortion,
    model_support,
    model_view,
    panel_edges,
    planar_pose,
    point_fit,
)
from estimators.warmup import compile_kernels

#: The compiled functions NumPy code calls (the others are compiled into these).
ENTRY_POINTS = [
    circle_edges._sample_circle,
    circle_fit._sampson_distances,
    clipped_noise._terms_array,
    corners._extrema_near,
    clipped_noise._moments_array,
    edge_fit._band_kernel,
    lens_distortion.distort,
    lens_distortion.refine_undistorted,
    lens_distortion.project_distorted,
    lens_distortion.visible_pixels,
    model_support._contour_samples,
    model_support._group_sums,
    model_view._outside_circles,
    panel_edges._strip_places,
    edge_fit._coarse_steps,
    edge_fit._lattice_kernel,
    edge_fit._lattice_samples,
    edge_fit._fit_offsets,
    edge_fit._robust_line,
    edge_search._strongest_peaks,
    least_squares._robust_sigma,
    least_squares._huber_group,
    least_squares._median,
    planar_pose._projection,
    planar_pose._whitened_reprojection,
    planar_pose._edge_residuals,
    planar_pose._edge_groups,
    planar_pose._whiten,
    point_fit._disc_model,
    point_fit._fit_discs_kernel,
    point_fit._normal_equations,
    point_fit._wedge_model,
    point_fit._wedge_levels,
    point_fit._fit_wedges_kernel,
]


def test_warm_up_compiles_every_compiled_entry_point_of_the_estimators():
    compile_kernels()
    assert [k.py_func.__name__ for k in ENTRY_POINTS if not k.signatures] == []


def test_every_compiled_kernel_of_the_estimators_divides_as_numpy_does():
    """A kernel that raised ZeroDivisionError where the NumPy code it replaced gave inf or NaN
    would turn a degenerate frame into an estimator fault, on which the supervisor stops the
    approach (``estimators.compiled``)."""
    import importlib
    import pkgutil

    from numba.core.registry import CPUDispatcher

    import estimators

    kernels = []
    for module in pkgutil.iter_modules(estimators.__path__):
        loaded = importlib.import_module(f"estimators.{module.name}")
        kernels += [v for v in vars(loaded).values() if isinstance(v, CPUDispatcher)]
    assert len({k.py_func for k in kernels}) >= 25
    wrong = [
        k.py_func.__qualname__ for k in kernels if k.targetoptions.get("error_model") != "numpy"
    ]
    assert wrong == []
