"""The one compiled part: robot_agent/slam/_kernels.c (the SLAM's hot loops). Optional: where no C
compiler is found the install goes on without it and the numpy versions run (kernels.py)."""

from setuptools import Extension, setup

setup(
    ext_modules=[
        Extension(
            "robot_agent.slam._kernels",
            ["robot_agent/slam/_kernels.c"],
            extra_compile_args=["-O2", "-ffp-contract=off"],
            optional=True,
        )
    ]
)
