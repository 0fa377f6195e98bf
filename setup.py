"""The one compiled part of MISS: the measurement's kernels (src/miss/measure/_nearest.cpp).

Everything else is in pyproject.toml. The extension is optional: where it cannot be built
(no C++ compiler), MISS measures with numba's kernels instead (see miss.measure._native).
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
        )
    ]
)
