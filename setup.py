"""The compiled parts of MISS: the measurement's kernels (src/miss/measure/_nearest.cpp) and
the placed edge collapse (src/miss/decimate/_placed.cpp).

Everything else is in pyproject.toml. Both extensions are optional: where they cannot be
built (no C++ compiler), MISS measures with numba's kernels instead (see
miss.measure._native) and collapses with numba's half-edge collapse (see
miss.decimate.placed).
"""

from setuptools import Extension, setup

setup(
    ext_modules=[
        Extension(
            "miss.measure._nearest",
            ["src/miss/measure/_nearest.cpp"],
            language="c++",
            # no fused multiply-adds: the same figures, to the bit, as numba's kernels
            extra_compile_args=["-O3", "-std=c++17", "-ffp-contract=off", "-pthread"],
            extra_link_args=["-pthread"],
            optional=True,
        ),
        Extension(
            "miss.decimate._placed",
            ["src/miss/decimate/_placed.cpp"],
            language="c++",
            extra_compile_args=["-O3", "-std=c++17", "-ffp-contract=off"],
            optional=True,
        ),
    ]
)
