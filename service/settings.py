"""Service settings: one pydantic-settings model, every field settable as ``RANDT_<NAME>``.

Lists take JSON (``RANDT_LISTEN='["tcp/127.0.0.1:7447"]'``), and ``randt serve``'s flags override
the environment. The nested groups ``matcher`` and ``registration`` take ``__`` per field
(``RANDT_MATCHER__MAX_RANGE_M=80``, tuples as JSON) or one JSON object; registration fields not
given keep the matcher's defaults (:data:`randt.core.odometry.MATCHER_REGISTRATION`), not pairwise
registration's. ``RANDT_ZENOH_CONFIG`` is read and checked here (docs/security.md). Built in the
app factory, never at import time; ``randt config`` lists every field (docs/deploy.md, "Environment").
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Annotated, Literal

from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    PrivateAttr,
    ValidationInfo,
    field_validator,
    model_validator,
)
from pydantic_settings import BaseSettings, SettingsConfigDict

from randt.core.config import RegistrationSettings
from randt.core.fleet_map import FleetMapSettings
from randt.core.odometry import MATCHER_REGISTRATION, MatcherSettings
from randt.wire.ids import ID_REGEX
from randt.wire.zenoh_config import check_endpoints, check_protocols, load_config_file

__all__ = ["DEFAULT_ROS2_ROUTER", "DEFAULT_ROS2_TOPICS", "Ros2Settings", "ServiceSettings"]


#: The matcher's finest NDT level, in map voxels (:meth:`ServiceSettings.session_matcher`): 1 m
#: with the default 0.2 m map voxel, near what ``auto_voxel_sizes`` finds on raw sweeps; of the
#: levels tried, the one where reduced sweeps track closest to raw ones, and cheaper than finer.
NDT_VOXELS_PER_MAP_VOXEL = 5.0


def _readable_config(value: Path | None) -> Path | None:
    """A missing or invalid Zenoh config file is one clear error, before anything starts."""
    if value is not None:
        load_config_file(value)
    return value


def _fits_config(path: Path | None, endpoints: tuple[str, ...]) -> None:
    """e.g. tcp/... endpoints with a TLS-only file: one error now, not Zenoh's at open."""
    if path is not None:
        check_protocols(load_config_file(path), endpoints, path)


#: Zenoh endpoints (``tcp/host:port``...), checked.
Endpoints = Annotated[tuple[str, ...], AfterValidator(check_endpoints)]
#: A native Zenoh config file that reads.
ZenohConfigFile = Annotated[Path | None, AfterValidator(_readable_config)]

_ROS_NAME = r"^/?[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*$"

#: The robots' router when neither ``ros2.connect`` nor the service's ``connect`` names one:
#: rmw_zenohd's port on this host.
DEFAULT_ROS2_ROUTER = "tcp/127.0.0.1:7447"

#: The PointCloud2 topics taken by default: ours, and the default topic of each common LiDAR
#: driver whose name stays one topic under a robot's namespace (docs/ros2.md lists those left out).
#: Relative, so ``/car9/velodyne_points`` is vehicle ``car9``; a driver whose default is absolute
#: (RoboSense's, Hesai's) publishes at the root unless its config is changed, and then needs its
#: vehicle named in ``vehicles``.
DEFAULT_ROS2_TOPICS = (
    "lidar/points",  # ours (docs/ros2.md)
    "velodyne_points",  # velodyne_pointcloud's convert and transform nodes (ros-drivers/velodyne)
    "ouster/points",  # ouster-ros: namespace ouster, topic points (its README)
    "rslidar_points",  # rslidar_sdk: ros_send_point_cloud_topic /rslidar_points (config/config.yaml)
    "lidar_points",  # HesaiLidar_ROS_2.0: ros_send_point_cloud_topic /lidar_points (config/config.yaml)
    "points_raw",  # Autoware.AI's and Autoware.Auto's raw LiDAR topic (/points_raw)
)


class Ros2Settings(BaseModel):
    """ROS 2 robots on rmw_zenoh (docs/ros2.md): ``RANDT_ROS2__<FIELD>``, or ``randt serve --ros2``.

    Names without a leading slash are relative to each robot's namespace: the robot in namespace
    ``/robot7`` publishing ``/robot7/lidar/points`` is vehicle ``robot7`` and hears its poses on
    ``/robot7/randt/odometry``."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    enabled: bool = Field(default=False, description="subscribe to the robots' PointCloud2 topics")
    connect: Endpoints | None = Field(
        default=None,
        description="the rmw_zenohd router(s) the service connects to, as a Zenoh client (rmw_zenoh's "
        "router forwards to clients, not between peers); None: the service's own `connect` endpoints "
        f"(and its zenoh_config, unless one is given here), or {DEFAULT_ROS2_ROUTER} without them",
    )
    zenoh_config: ZenohConfigFile = Field(
        default=None,
        description="a native Zenoh config file for the session to the router (TLS, user/password: "
        "docs/security.md); its mode and connect endpoints are replaced by client and `connect`",
    )
    domain: int = Field(default=0, ge=0, le=232, description="ROS_DOMAIN_ID of the robots")
    topics: tuple[str, ...] = Field(
        default=DEFAULT_ROS2_TOPICS,
        min_length=1,
        description="PointCloud2 topics: relative (under any namespace, which names the vehicle) or "
        "absolute (one topic; its vehicle from `vehicles`); by default ours and the common LiDAR "
        "drivers' defaults (docs/ros2.md); a PointCloud2 topic not taken is named once in the log",
    )
    vehicles: dict[str, str] = Field(
        default_factory=dict,
        description="namespace or absolute topic -> vehicle id, where the namespace is not the id "
        "(e.g. {\"/\": \"robot7\"} for a robot without a namespace); default: the namespace, '/' as '.'",
    )
    odometry_topic: str = Field(default="randt/odometry", pattern=_ROS_NAME)
    correction_topic: str = Field(default="randt/correction", pattern=_ROS_NAME)
    status_topic: str = Field(default="randt/status", pattern=_ROS_NAME)
    map_frame: str = Field(default="map", min_length=1, description="the corrections' parent frame")
    odom_frame: str = Field(
        default="randt_odom",
        min_length=1,
        description="the frame of the Odometry poses (the session's, as answered); map_frame -> "
        "odom_frame is the correction",
    )
    sensor_frame: str | None = Field(
        default=None, description="the Odometry child_frame_id; None: the PointCloud2's frame_id"
    )
    gnss_topic: str | None = Field(
        default="gnss/fix",
        pattern=_ROS_NAME,
        description="the robots' sensor_msgs/NavSatFix (relative: under each namespace; null: none): "
        "a fix within gnss_max_gap_s of a scan goes to the pose graph with it, which places the "
        "session in the shared map by its fixes and fuses them (docs/ros2.md)",
    )
    gnss_max_gap_s: float = Field(
        default=0.1, gt=0, le=1.0, description="a fix this far in time from a scan's stamp is not its"
    )
    map_request_topic: str = Field(
        default="randt/map_request",
        pattern=_ROS_NAME,
        description="a geometry_msgs/PointStamped here asks for the map around its point, answered "
        "as one sensor_msgs/PointCloud2 on map_topic (docs/ros2.md)",
    )
    map_topic: str = Field(default="randt/map", pattern=_ROS_NAME)
    localize_only: frozenset[str] = Field(
        default=frozenset(),
        description='vehicle ids ("*": every robot) whose sessions only localize on the shared map and '
        "never add to it (docs/clients.md, a session that only localizes): a robot sends no prior, so it "
        "is relocalized on the map (docs/mapping.md); until then, and off the map, its scans are "
        "answered not_on_map on its status topic",
    )
    map_radius_m: float = Field(
        default=100.0, gt=0, le=1000.0, description="the map tiles within this of the requested point"
    )

    #: the fields ServiceSettings filled from its own because they were not given here
    _from_service: frozenset[str] = PrivateAttr(default=frozenset())

    @property
    def from_service(self) -> frozenset[str]:
        """The fields (``connect``, ``zenoh_config``) :class:`ServiceSettings` filled from its own
        because they were not given: a router given later (``--ros2-connect``) takes neither."""
        return self._from_service

    @property
    def routers(self) -> tuple[str, ...]:
        """The endpoints the ROS 2 session connects to: ``connect``, or :data:`DEFAULT_ROS2_ROUTER`
        (:class:`ServiceSettings` has put its own ``connect`` there when this one was not given)."""
        return self.connect if self.connect is not None else (DEFAULT_ROS2_ROUTER,)

    @model_validator(mode="after")
    def _endpoints_fit_the_config_file(self) -> Ros2Settings:
        if self.connect is not None:  # (else ServiceSettings checks, once it has named the routers)
            _fits_config(self.zenoh_config, self.connect)
        return self

    @field_validator("topics")
    @classmethod
    def _topics(cls, value: tuple[str, ...]) -> tuple[str, ...]:
        for topic in value:
            if not re.fullmatch(_ROS_NAME, topic):
                raise ValueError(f"{topic!r} is not a ROS 2 topic name")
        return value

    @field_validator("vehicles")
    @classmethod
    def _vehicle_ids(cls, value: dict[str, str]) -> dict[str, str]:
        for name, vehicle in value.items():
            if not re.fullmatch(ID_REGEX, vehicle):
                raise ValueError(f"vehicles[{name!r}]: {vehicle!r} is not a vehicle id")
        return value


class ServiceSettings(BaseSettings):
    """Everything ``randt serve`` needs; defaults run embedded on one machine, no router."""

    model_config = SettingsConfigDict(
        env_prefix="RANDT_", env_nested_delimiter="__", extra="forbid", frozen=True
    )

    data_dir: Path = Field(default=Path("randt-data"), description="maps, trajectories, session state")
    instance: str = Field(default="randt-1", pattern=ID_REGEX)
    # Zenoh
    zenoh_mode: Literal["peer", "client"] = "peer"
    listen: Endpoints = Field(default=("tcp/127.0.0.1:7447",), description="Zenoh endpoints")
    connect: Endpoints = Field(default=(), description="routers or peers to connect to")
    # Zenoh security (docs/security.md)
    zenoh_config: ZenohConfigFile = Field(
        default=None,
        description="native Zenoh JSON5 config file (TLS, mTLS, user/password, access control); "
        "mode, listen and connect still come from these settings",
    )
    # HTTP
    http_host: str = "127.0.0.1"
    http_port: int = Field(default=8080, ge=0, le=65535)
    api_token: str | None = Field(
        default=None, min_length=16, description="bearer token of mutating endpoints; none: they are refused"
    )
    protect_reads: bool = Field(
        default=False, description="read endpoints (not /healthz, /readyz) require the token too"
    )
    # sessions
    queue_size: int = Field(
        default=8, ge=1, description="scans waiting per session; beyond, one is shed (evenly over time)"
    )
    max_sessions: int = Field(
        default=-1,
        ge=-1,
        description="running sessions at most; a scan that would open one more is refused "
        "(sessions_full): -1 = 4 per core (8 on 2 cores), 0 = no limit",
    )
    capacity_target: float = Field(
        default=0.6,
        ge=0,
        le=1,
        description="admission by measured capacity (service/capacity.py): a scan that would open a "
        "session is refused (sessions_full, with retry_after_s) when the running sessions' measured "
        "CPU (rate x CPU per sweep) and a new one's expected share would pass this share of the "
        "cores (the Ray cluster's with executor ray); 0 = by max_sessions only",
    )
    session_rate_hz: float = Field(
        default=10.0, gt=0, description="scan rate a new or not yet measured session is expected to send"
    )
    sweep_cpu_estimate_s: float = Field(
        default=0.09,
        gt=0,
        description="matcher CPU per sweep a new session is expected to cost until a session has been "
        "measured (then the measured sessions' mean); 0.09: a reduced simulated sweep's matcher work "
        "in the service, with room for the service's and the pose graph's until those are measured",
    )
    admission_retry_s: float = Field(
        default=10.0, gt=0, description="retry_after_s told to a vehicle refused for lack of capacity"
    )
    idle_expiry_s: float = Field(default=120.0, gt=0, description="an idle session is saved and closed")
    # intake and fair admission (service/intake.py, service/admission.py)
    intake_workers: int = Field(
        default=2, ge=1, description="threads decoding and admitting scans, vehicles served round-robin"
    )
    intake_queue_scans: int = Field(
        default=16, ge=1, description="undecoded scans waiting per vehicle; beyond, its oldest is dropped"
    )
    intake_queue_bytes: int = Field(
        default=64 * 1024 * 1024,
        ge=1024,
        description="bytes of undecoded scans waiting per vehicle (one scan is always admitted)",
    )
    intake_total_bytes: int = Field(
        default=512 * 1024 * 1024,
        ge=1024,
        description="bytes of undecoded scans waiting over all vehicles; the largest queue loses its oldest",
    )
    max_sessions_per_vehicle: int = Field(
        default=2, ge=0, description="running sessions per vehicle (then vehicle_sessions_full); 0 = no limit"
    )
    vehicle_slot_idle_s: float = Field(
        default=1.0,
        gt=0,
        description="at the per-vehicle limit, the vehicle's own session idle this long gives its "
        "slot to the vehicle's new session (saved as expired)",
    )
    slot_idle_s: float = Field(
        default=10.0,
        gt=0,
        description="a session idle this long gives its slot to a new one when a limit is reached "
        "(saved as expired; it resumes with its next scan)",
    )
    fallback_horizon_s: float = Field(
        default=0.5,
        gt=0,
        description="a scan that does not match is answered with the motion prediction (status "
        "fallback) only while the session's last match is at most this old (scan stamps); after that "
        "the session is lost: answered `lost` without a pose, folding nothing, until two consecutive "
        "matches agree",
    )
    matcher_processes: int = Field(
        default=-1,
        ge=-1,
        description="worker processes running the matchers: -1 = one per core (none on one core), "
        "0 = run them in the session threads (service/matchers.py)",
    )
    executor: Literal["local", "ray"] = Field(
        default="local",
        description="where the sessions' matchers run: local worker processes (matcher_processes), "
        "or matcher host actors (one per CPU of each node) across a Ray cluster "
        "(service/ray_executor.py; the ray extra)",
    )
    ray_address: str | None = Field(
        default=None,
        description="with executor ray: the cluster to join (host:port or ray://...); none starts a "
        "local Ray",
    )
    ray_transport: Literal["socket", "ray"] = Field(
        default="socket",
        description="with executor ray: how sweeps reach the matcher hosts: a TCP connection from "
        "the service to each host, placed and supervised by Ray (socket: the service must reach "
        "the nodes on ephemeral ports), or a Ray actor call per sweep (ray: slower, Ray's ports only)",
    )
    # map
    default_map: str = Field(
        default="default",
        pattern=r"^[A-Za-z0-9][A-Za-z0-9_-]{0,63}$",
        description="the shared map (sessions with prior poses); an id without a dot, since every "
        "session's own map has one (randt.wire.ids.session_map_name)",
    )
    map_origin: tuple[float, float, float] | None = Field(
        default=None,
        description="the shared map's geodetic origin: latitude, longitude (deg, WGS84), height above "
        "the ellipsoid (m), e.g. RANDT_MAP_ORIGIN='[48.137, 11.575, 520]'; unset: the first WGS84 "
        "prior (geo_prior) sets it (docs/mapping.md, Georeferenced maps)",
    )
    tile_size_m: int = Field(default=20, ge=1)
    map_voxel_m: float = Field(default=0.2, gt=0)
    flush_interval_s: float = Field(
        default=1.0,
        gt=0,
        description="the flusher's period: sessions whose snapshot is due are saved, idle ones expired",
    )
    snapshot_interval_s: float = Field(
        default=30.0,
        gt=0,
        description="a running session's snapshot (its matcher state and its record) is "
        "written when it opens and ends, and in between at most this often (or after "
        "snapshot_distance_m); its pose log holds every acknowledged pose meanwhile",
    )
    snapshot_distance_m: float = Field(
        default=20.0,
        ge=0,
        description="a running session's snapshot is also due once its vehicle is this far from where "
        "the last one was taken: after a crash the session resumes against the snapshot's keyframes, "
        "which reach only so far (docs/architecture.md, The store), and a recent sweep the flusher "
        "saved (resume.npz) (0: by time only)",
    )
    tile_save_interval_s: float | None = Field(
        default=None,
        gt=0,
        description="dirty tiles saved and published (at the first flush this long after the last "
        "save; None: every third flush, 3 s by default): a vehicle's sweeps touch the same tiles for "
        "seconds, and each save writes and publishes a tile whole",
    )
    map_agreement_min: float = Field(
        default=0.4,
        ge=0,
        le=1,
        description="a session's map points are folded only while its sweeps agree with the map "
        "where the map has content: at least this share of a checked sweep's points above the "
        "ground within 0.5 m of the map's points (service/agreement.py); below it the session is "
        "lost until two checks agree, and the points since the last check are dropped; 0 = off",
    )
    map_agreement_every: int = Field(
        default=10,
        ge=1,
        description="a session's sweeps are checked against its map every this many sweeps (and "
        "every keyframe the pose graph takes); its map points wait for the next check",
    )
    map_agreement_min_points: int = Field(
        default=2000,
        ge=1,
        description="a check has an opinion only when this many of the sweep's points fall where "
        "the map has content; with fewer the held points are folded",
    )
    fold_scans: int = Field(
        default=10,
        ge=1,
        description="a session's map points enter the map's tiles every this many scans, and before "
        "every save (tiles are served as saved, so no one outside sees the difference)",
    )
    ndt_levels_from_map: bool = Field(
        default=True,
        description="every session's NDT levels from map_voxel_m (finest 5 map voxels); false: each "
        "session derives them from its first sweep, as `randt map` does (ServiceSettings.session_matcher)",
    )
    # localizing on the map (service/localizing.py, docs/mapping.md "Localizing on the map")
    localize: bool = Field(
        default=False,
        description="a session in the shared map whose surroundings are in it matches its sweeps on the "
        "map around the vehicle instead of its own keyframes (no drift, no model update); where the map "
        "has too little it maps",
    )
    localize_radius_m: float = Field(
        default=80.0, gt=0, description="the map around the vehicle it localizes on"
    )
    localize_first_radius_m: float = Field(
        default=50.0,
        gt=0,
        description="the radius of a session's first window (at most localize_radius_m): a session's "
        "start prepares fewer tiles; the whole window follows after a travel of localize_reload_m less "
        "the difference of the radii",
    )
    localize_reload_m: float = Field(
        default=40.0,
        gt=0,
        description="travel from the window's centre before the window is cut again (half the radius: "
        "the sensor's reach is still inside it)",
    )
    localize_min_map_points: int = Field(
        default=20000, ge=1, description="fewer map points around the vehicle: the session maps there"
    )
    # pose graph (service/graph.py, docs/mapping.md)
    graph: bool = Field(
        default=True,
        description="pose graphs, one per map (loop closure, GNSS fusion), in a process of its own; "
        "corrections on randt/fleet/<vehicle>/correction (docs/mapping.md)",
    )
    graph_keyframe_m: float = Field(default=10.0, gt=0, description="travel between graph keyframes")
    graph_queue: int = Field(
        default=64, ge=1, description="keyframes waiting for the graph process; beyond, the oldest is dropped"
    )
    graph_refold_s: float = Field(
        default=20.0,
        ge=0,
        description="at most this often, in a pause between keyframes, the graph process re-folds the "
        "tiles of keyframes it moved (0: after every keyframe)",
    )
    graph_yield: bool | None = Field(
        default=None,
        description="the graph process is stopped while sweeps are being matched (held at most 1 s "
        "without a break): the matchers' latency does not pay for it (service/graph.py, YieldGate); "
        "None: on with the local executor, off with Ray (the matchers are elsewhere)",
    )
    fleet_map: FleetMapSettings = Field(
        default_factory=FleetMapSettings, description="the pose graph's settings (randt.core.fleet_map)"
    )
    # wire limits
    max_points: int = Field(default=300_000, ge=1)
    max_payload_bytes: int = Field(default=16 * 1024 * 1024, ge=1024)
    # every session's matcher (module docstring: RANDT_MATCHER__<FIELD>, RANDT_REGISTRATION__<FIELD>)
    matcher: MatcherSettings = Field(
        default_factory=MatcherSettings, description="the incremental matcher (Algorithm 2) of every session"
    )
    registration: RegistrationSettings = Field(
        default=MATCHER_REGISTRATION,
        description="the matcher's NDT registration; fields not given keep the matcher's defaults",
    )
    ros2: Ros2Settings = Field(
        default_factory=Ros2Settings, description="ROS 2 robots on rmw_zenoh (docs/ros2.md)"
    )

    @property
    def tile_save_s(self) -> float:
        """Seconds between two saves of the dirty tiles (``tile_save_interval_s``, by default three
        flush intervals)."""
        return 3.0 * self.flush_interval_s if self.tile_save_interval_s is None else self.tile_save_interval_s

    def session_matcher(self) -> MatcherSettings:
        """The matcher settings every session gets: :attr:`matcher`, with NDT levels tied to the map.

        Unless levels are given (``RANDT_MATCHER__VOXEL_SIZES_M`` or
        ``RANDT_REGISTRATION__VOXEL_SIZES_M``) or ``ndt_levels_from_map`` is off, the finest is
        :data:`NDT_VOXELS_PER_MAP_VOXEL` map voxels (1 m with the default 0.2 m map voxel; the
        levels are (16r, 8r, 4r, 2r, r)). The matcher alone would derive them from a session's
        first sweep (``auto_voxel_sizes``), and that estimate depends on the sweep's point density:
        a sweep the vehicle library reduced gets coarser levels than its raw sweep, which put the
        reduced session's trajectory off the raw one's (docs/benchmarks.md, "Vehicle link"). Tied
        to the map, raw and reduced sweeps match at the same scale.
        """
        given = self.matcher.voxel_sizes_m is not None or self.registration.voxel_sizes_m is not None
        if given or not self.ndt_levels_from_map:
            return self.matcher
        r = NDT_VOXELS_PER_MAP_VOXEL * self.map_voxel_m
        return self.matcher.model_copy(update={"voxel_sizes_m": (16 * r, 8 * r, 4 * r, 2 * r, r)})

    @field_validator("registration", mode="before")
    @classmethod
    def _matcher_registration_defaults(cls, value: object) -> object:
        """Fields given as a mapping (the environment, JSON) start from the matcher's defaults."""
        if isinstance(value, dict):
            return {**MATCHER_REGISTRATION.model_dump(exclude_defaults=True), **value}
        return value

    @field_validator("ros2")
    @classmethod
    def _ros2_router_defaults_to_ours(cls, value: Ros2Settings, info: ValidationInfo) -> Ros2Settings:
        """``ros2.connect`` not given: the ROS 2 session goes where the service's own session
        connects (``connect``, with its ``zenoh_config`` unless ``ros2`` names one), so that
        ``randt serve --ros2 --connect tcp/R:P`` reaches the robots' router R."""
        connect, zenoh_config = info.data.get("connect"), info.data.get("zenoh_config")
        if value.connect is not None:
            return value
        if not connect:
            _fits_config(value.zenoh_config, value.routers)
            return value
        filled = {"connect": connect}
        if value.zenoh_config is None and zenoh_config is not None:
            filled["zenoh_config"] = zenoh_config
        resolved = Ros2Settings.model_validate({**value.model_dump(), **filled})
        resolved._from_service = frozenset(filled)
        return resolved

    @model_validator(mode="after")
    def _endpoints_fit_the_config_file(self) -> ServiceSettings:
        _fits_config(self.zenoh_config, self.listen + self.connect)
        return self

    @model_validator(mode="after")
    def _reads_need_a_token(self) -> ServiceSettings:
        if self.protect_reads and not self.api_token:
            raise ValueError("protect_reads needs api_token (RANDT_API_TOKEN): reads would be closed to all")
        return self
