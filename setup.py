"""Package discovery for the two top-level folders that the design card names (daemon/, sitl/).

pyproject.toml maps them into the ``gps_denied_onboard`` import root; setuptools' automatic discovery
cannot see mapped folders, so the package list is built here.
"""

from setuptools import find_packages, setup

_MAPPED = {"gps_denied_onboard.daemon": "daemon", "gps_denied_onboard.sitl": "sitl"}

packages = find_packages("src")
for name, folder in _MAPPED.items():
    packages.append(name)
    packages += [f"{name}.{sub}" for sub in find_packages(folder)]
# Folders of package data with no __init__.py (sitl/scenarios/*.yaml): Python can import them as namespace
# packages, and setuptools warns ("Package would be ignored") unless they are listed as packages too.
packages += ["gps_denied_onboard.sitl.scenarios"]

setup(packages=packages)
