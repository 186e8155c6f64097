"""Package discovery plus one mapping pyproject.toml cannot state next to discovery.

The shipped configs and EDS files stay in the top-level ``config/`` folder (the copy users
read and edit), the service files in ``deploy/`` and the documents in ``docs/``; the wheel
carries them as the package data ``gateway/data/`` (``deploy/``, ``docs/`` below it), found
at run time with importlib.resources (``gateway/core/resources.py``). Everything else is in
pyproject.toml.
"""

from setuptools import find_packages, setup

# Each folder of config/ is a package of its own (setuptools warns, 40 lines on every
# install, about data in a folder that is not a listed package: gateway.data.calibrate).
DATA = {
    "gateway.data": "config",
    "gateway.data.calibrate": "config/calibrate",
    # `cdpr-gateway examples deploy DIR`: the service files, and the documents the unit's
    # Documentation= points at, come from the installed package
    "gateway.data.deploy": "deploy",
    "gateway.data.deploy.site": "deploy/site",
    "gateway.data.docs": "docs",
}

setup(
    packages=[*find_packages(include=["gateway*", "drivers*", "sim_plc*"]), *DATA],
    package_dir=DATA,
    package_data={
        "gateway": ["py.typed"],
        "gateway.data": ["*.yaml", "*.eds"],
        "gateway.data.calibrate": ["*.yaml"],
        "gateway.data.deploy": ["*.yml", "*.json", "*.service"],
        "gateway.data.deploy.site": ["*.yml"],
        "gateway.data.docs": ["*.md", "*.json"],
    },
)
