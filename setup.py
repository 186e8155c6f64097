"""Package discovery plus one mapping pyproject.toml cannot state next to discovery.

The shipped configs and EDS files stay in the top-level ``config/`` folder (the copy users
read and edit); the wheel carries them as the package data ``gateway/data/``, found at run
time with importlib.resources (``gateway/core/resources.py``). Everything else is in
pyproject.toml.
"""

from setuptools import find_packages, setup

setup(
    packages=[*find_packages(include=["gateway*", "drivers*", "sim_plc*"]), "gateway.data"],
    package_dir={"gateway.data": "config"},
    package_data={
        "gateway": ["py.typed"],
        "sim_plc": ["scenarios.yaml", "scenarios_sealed.yaml"],
        "gateway.data": ["*.yaml", "*.eds", "calibrate/*.yaml"],
    },
)
