"""The compiled parts: robot_agent/slam/_kernels.c (the SLAM's hot loops) and shared/_kernels.c
(the map server's nearest-sample index). Optional: where no C compiler is found the install goes
on without them and the numpy versions run (robot_agent/slam/kernels.py, shared/kernels.py)."""

from setuptools import Extension, setup

FLAGS = ["-O2", "-ffp-contract=off"]
HEADERS = ["shared/_common.h"]

setup(
    ext_modules=[
        Extension(
            "robot_agent.slam._kernels",
            ["robot_agent/slam/_kernels.c"],
            include_dirs=["shared"],
            depends=HEADERS,
            extra_compile_args=FLAGS,
            optional=True,
        ),
        Extension(
            "shared._kernels",
            ["shared/_kernels.c"],
            depends=HEADERS,
            extra_compile_args=FLAGS,
            optional=True,
        ),
    ]
)
