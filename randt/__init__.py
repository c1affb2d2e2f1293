"""randt-fleet: a streaming map builder for vehicle fleets, RANDT scan matching over Eclipse Zenoh.

One import name for the whole distribution; each subpackage is a folder at the repository's top
(``pyproject.toml`` maps them): :mod:`randt.core` (arrays in, results out: registration, the
incremental matcher, tiles, metrics, formats), :mod:`randt.wire` (the messages vehicles and the
service share), :mod:`randt.service` (the fleet service), :mod:`randt.clients` (vehicle library,
replay, REST client), :mod:`randt.sim` (the LiDAR fleet simulator) and :mod:`randt.cli` (the
``randt`` command). ``docs/architecture.md`` draws the layers.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("randt-fleet")
except PackageNotFoundError:  # the sources on sys.path without an install
    __version__ = "0+unknown"
