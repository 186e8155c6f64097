"""The gateway's configuration: YAML -> frozen dataclasses, validated once at start.

``load_config(path)`` reads a full config file (``config/default.yaml`` is the reference).
Every section has defaults, so a file only states what differs. Unknown keys and bad
values raise :class:`ConfigError` naming the file and the dotted key. The ``sim_plc``
section belongs to the soft PLC: it is kept as a raw mapping here and validated by
``sim_plc`` when the soft PLC loads it.
"""

from __future__ import annotations

import dataclasses
import ipaddress
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, Literal

from gateway.core.configtypes import Ranged, convert, read_yaml, require
from gateway.core.registermap import (
    RegisterMap,
)
from gateway.core.resources import data_file, resolve_beside
from gateway.errors import ConfigError

if TYPE_CHECKING:
    from gateway.model.effects.registry import Effects

Vec3 = tuple[float, float, float]
Ranges = dict[str, tuple[float, float]]  # per numeric field: (low, high), inclusive
TWO_PI = 2 * math.pi

DEFAULT_CONFIG_PATH = data_file("default.yaml")  # config/ in a checkout, package data in a wheel


@dataclass(frozen=True)
class GeometryConfig(Ranged):
    """Frame anchors ``a_i`` (world frame, m) and platform anchors ``b_i`` (platform frame)."""

    # a_i: where each cable leaves the frame (world frame, one per cable)
    frame_anchors_m: tuple[Vec3, ...]
    # b_i: where each cable meets the platform (platform frame)
    platform_anchors_m: tuple[Vec3, ...]
    # the platform with its load (the PLC may send it: registers.platform_mass)
    platform_mass_kg: float = 40.0
    gravity_m_s2: float = 9.81  # along -z of the world frame
    center_of_mass_m: Vec3 = (0.0, 0.0, 0.0)  # the platform's centre of mass in the platform frame
    # x, y, z (m), rx, ry, rz (rad): where the soft PLC and the checks start
    home_pose: tuple[float, float, float, float, float, float] = (0.0, 0.0, 1.5, 0.0, 0.0, 0.0)
    RANGES: ClassVar[Ranges] = {
        "frame_anchors_m": (-1e3, 1e3),
        "platform_anchors_m": (-1e2, 1e2),
        "platform_mass_kg": (1e-3, 1e5),
        "gravity_m_s2": (0.0, 100.0),
        "center_of_mass_m": (-1e2, 1e2),
        "home_pose": (-1e3, 1e3),
    }

    def __post_init__(self) -> None:
        super().__post_init__()
        require(len(self.frame_anchors_m) >= 1, "frame_anchors_m: at least one cable")
        require(
            len(self.frame_anchors_m) == len(self.platform_anchors_m),
            f"frame_anchors_m has {len(self.frame_anchors_m)} entries but platform_anchors_m "
            f"has {len(self.platform_anchors_m)}",
        )

    @property
    def cables(self) -> int:
        return len(self.frame_anchors_m)


@dataclass(frozen=True)
class TensionConfig(Ranged):
    """Admissible cable tensions for the tension distribution (paper: 0 < T < 1000 N)."""

    min_n: float = 20.0  # lowest cable tension the distribution may choose
    max_n: float = 490.0  # highest cable tension the distribution may choose
    RANGES: ClassVar[Ranges] = {"min_n": (0.0, 1e6), "max_n": (0.0, 1e6)}

    def __post_init__(self) -> None:
        super().__post_init__()
        require(0 <= self.min_n < self.max_n, "need 0 <= min_n < max_n")


@dataclass(frozen=True)
class SensorConfig(Ranged):
    """The force sensors: range and the S7 analog format (0..adc_full_scale = 0..range)."""

    range_n: float = 500.0  # the force sensors' full range
    adc_full_scale: int = 27648  # the raw count at full range (S7 analog: 27648)
    RANGES: ClassVar[Ranges] = {"range_n": (1e-3, 1e6), "adc_full_scale": (1, 32767)}


@dataclass(frozen=True)
class PulleyConfig(Ranged):
    """One pulley between sensor and platform: wrap (deflection) angle and bearing mu."""

    wrap_deg: float
    mu: float
    RANGES: ClassVar[Ranges] = {"wrap_deg": (0.0, 180.0), "mu": (0.0, 0.999)}


EffectParams = dict[str, float | tuple[float, ...]]


def _effect_values(
    raw: dict[str, EffectParams], cables: int, pulley_radius_m: float, where: str
) -> Effects:
    """``raw`` (the plain mapping the config holds) as the effects registry's per-cable
    arrays, checked by the registry (ValueError naming the key). The model layer is
    imported here, when a config has effects to check or a caller asks for their values:
    the config itself stands on nothing that loads numba or the compiled kernels."""
    if not raw:
        return {}
    from gateway.model.effects.registry import effect_values

    return effect_values(raw, cables, pulley_radius_m, where)


@dataclass(frozen=True)
class FrictionConfig(Ranged):
    """The pulley friction model (docs/recording-format.md, 'The nominal model file').

    ``effects``: optional fitted effects (what ``diagnose --write-model`` writes), by the
    ids and parameter names of the effects registry (:mod:`gateway.model.effects`), each
    parameter a scalar for every cable or a list with one value per cable, e.g.
    ``effects: {viscous: {c_ns_m: 0.4}, offset: {c_n: [0.3, -0.2, ...]}}``. Unknown effects
    or parameters are errors naming the key; list lengths are checked against the cable
    count where the geometry is known (:class:`Config`, :meth:`effect_values`).
    """

    # per pulley: no friction, Coulomb bearing friction, or the Dahl pre-sliding state
    model: Literal["none", "coulomb", "dahl"] = "dahl"
    pulleys: tuple[PulleyConfig, ...] = (
        PulleyConfig(90.0, 0.015),
        PulleyConfig(60.0, 0.015),
        PulleyConfig(30.0, 0.015),
    )
    sigma_n_m: float = 500.0  # Dahl stiffness: how fast the pre-sliding force builds up with travel
    beta: float = 1.0  # Dahl shape exponent (1: the classic exponential)
    viscous_ns_m: float = 0.0  # viscous friction per pulley, force per cable speed
    pulley_radius_m: float = 0.05  # pulley radius (effects with a rotation angle use it)
    # fitted effects by registry name (diagnose --write-model writes them; docs/physics.md sec. 4)
    effects: dict[str, EffectParams] = field(default_factory=dict)
    # the effects' parameters are checked by the effects registry (effect_values)
    RANGES: ClassVar[Ranges] = {
        "sigma_n_m": (1e-6, 1e9),
        "beta": (1e-3, 100.0),
        "viscous_ns_m": (0.0, 1e6),
        "pulley_radius_m": (1e-4, 10.0),
    }

    def __post_init__(self) -> None:
        super().__post_init__()
        for name, params in self.effects.items():
            sizes = {len(v) for v in params.values() if isinstance(v, tuple | list)}
            if len(sizes) > 1:
                raise ValueError(f"effects.{name}: per-cable lists of different lengths")
            _effect_values(
                {name: params}, sizes.pop() if sizes else 1, self.pulley_radius_m, "effects"
            )

    @property
    def wrap_rad(self) -> tuple[float, ...]:
        return tuple(math.radians(p.wrap_deg) for p in self.pulleys)

    @property
    def mu(self) -> tuple[float, ...]:
        return tuple(p.mu for p in self.pulleys)

    def effect_values(self, cables: int) -> Effects:
        """The fitted effects as per-cable arrays (ValueError naming the key if a list
        does not have ``cables`` values)."""
        return _effect_values(self.effects, cables, self.pulley_radius_m, "friction.effects")

    def to_mapping(self) -> dict[str, Any]:
        """The ``friction:`` mapping as YAML would hold it (``load_friction`` reads it back)."""
        out: dict[str, Any] = {
            "model": self.model,
            "pulleys": [{"wrap_deg": p.wrap_deg, "mu": p.mu} for p in self.pulleys],
            "sigma_n_m": self.sigma_n_m,
            "beta": self.beta,
            "viscous_ns_m": self.viscous_ns_m,
            "pulley_radius_m": self.pulley_radius_m,
        }
        if self.effects:
            out["effects"] = {
                name: {
                    k: (list(v) if isinstance(v, tuple | list) else v) for k, v in params.items()
                }
                for name, params in self.effects.items()
            }
        return out

    @staticmethod
    def effects_mapping(values: Effects) -> dict[str, EffectParams]:
        """Per-cable arrays -> the ``effects`` field's form (scalar where cables agree)."""
        from gateway.model.effects.registry import to_mapping as effects_to_mapping

        return {
            name: {k: (tuple(v) if isinstance(v, list) else v) for k, v in params.items()}
            for name, params in effects_to_mapping(values).items()
        }


@dataclass(frozen=True)
class RealtimeConfig(Ranged):
    """``loop.realtime``: real-time settings ``run`` applies to its loop at start where the
    process may (:mod:`gateway.runtime.realtime`); what is refused is logged in one line,
    never fatal. On by default (a 1 kHz service); ``enabled: false`` leaves the process
    as it was started."""

    enabled: bool = True  # try the real-time settings below at start (what is refused is logged)
    policy: Literal["fifo", "rr", "other"] = "fifo"  # SCHED_FIFO, SCHED_RR, SCHED_OTHER
    priority: int = 50  # 1..99 for fifo and rr
    cpus: tuple[int, ...] = ()  # CPU affinity of the cycle's thread; () leaves it as is
    lock_memory: bool = True  # mlockall(MCL_CURRENT | MCL_FUTURE): no page faults
    gc_off: bool = True  # after the start-up gc.freeze(), no garbage collection at all
    # held in /dev/cpu_dma_latency while running: idle CPUs poll instead of halting, so a
    # wake-up (the next deadline, the PLC's reply) is not delayed by leaving a sleep state;
    # None leaves the CPUs' idle states alone
    cpu_dma_latency_us: int | None = 0
    RANGES: ClassVar[Ranges] = {
        "priority": (0, 99),
        "cpus": (0, 4095),
        "cpu_dma_latency_us": (0, 2_000_000_000),
    }

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.policy != "other":
            require(1 <= self.priority <= 99, "priority must be in 1..99 for fifo and rr")
        require(len(set(self.cpus)) == len(self.cpus), "cpus must not repeat a CPU")


@dataclass(frozen=True)
class HeartbeatConfig(Ranged):
    """``loop.heartbeat``: what the PLC heartbeat register says about the PLC's samples,
    the one source of the time step of the compensation (gateway/runtime/clock.py).

    ``counter``: it counts PLC samples, wrapping at ``modulus`` (None: the register's
    range; a float32 register counts without a wrap); ``toggle``: it changes every PLC
    cycle of ``period_s`` (a 0/1 life bit; None: ``loop.period_s``); ``none``: it carries
    no timing and the gateway's own clock is used. The watchdog
    (``loop.heartbeat_timeout_s``) watches it whatever the kind."""

    kind: Literal["counter", "toggle", "none"] = "counter"  # what the register does
    modulus: int | None = None  # counter: it wraps here (null: the register's range)
    period_s: float | None = None  # toggle: the PLC cycle it changes every (null: period_s)
    RANGES: ClassVar[Ranges] = {"modulus": (2, 2**32), "period_s": (1e-5, 1.0)}

    def __post_init__(self) -> None:
        super().__post_init__()
        require(self.kind == "counter" or self.modulus is None, "modulus: only for a counter")
        require(self.kind == "toggle" or self.period_s is None, "period_s: only for a toggle")


# The averaged PLC sample spacing may be this far off (relative) the PLC's rate over a gap
# when a count is held against the gateway's clock (gateway/runtime/clock.py). Generous on
# purpose: the average takes spacings up to 3x off it, a soft PLC's counting thread on a
# loaded machine changes its rate by tens of percent, and a count refused for nothing leaves
# the cables cold for seconds; what it lets through is a count at most 1.5 (e + L) long.
SPACING_TOLERANCE = 0.5
HEARTBEAT_VALUES = {"int16": 2**16, "uint16": 2**16, "int32": 2**32, "uint32": 2**32}
FLOAT32_EXACT = 2**24  # a float32 holds every integer up to this, not beyond


@dataclass(frozen=True)
class LoopConfig(Ranged):
    """The cyclic service: period, channel validation and the PLC watchdog."""

    period_s: float = 0.001  # the cycle: one read, compensation and write every period
    substitute_max_s: float = 0.05  # last-good substitution lasts at most this, then invalid
    stuck_after_s: float = 0.5  # a channel that does not change for this long is stuck
    stale_after_s: float = 0.01  # no fresh read for this long: channels are stale
    heartbeat_timeout_s: float = 0.1  # PLC heartbeat unchanged this long: stop writing, fault
    # a value goes out good only if computed from PLC data this young when sent (the
    # output gate, drivers/gate.py); None: stale_after_s (input_age_limit_s)
    max_input_age_s: float | None = None
    fixed_point_tol_n: float = 1e-9  # the chain's implicit tension solve stops at this change
    fixed_point_max_iter: int = 8  # ... or after this many iterations
    # changed counters are summed up in the log at most this often
    overrun_warning_interval_s: float = 10.0
    busy_wait_s: float = 0.0002  # spin this long before each deadline instead of sleeping
    realtime: RealtimeConfig = field(default_factory=RealtimeConfig)
    heartbeat: HeartbeatConfig = field(default_factory=HeartbeatConfig)
    RANGES: ClassVar[Ranges] = {
        "period_s": (1e-4, 1.0),
        "substitute_max_s": (0.0, 10.0),
        "stuck_after_s": (1e-3, 3600.0),
        "stale_after_s": (1e-4, 60.0),
        "heartbeat_timeout_s": (1e-3, 60.0),
        "max_input_age_s": (1e-4, 10.0),
        "fixed_point_tol_n": (1e-15, 1.0),
        "fixed_point_max_iter": (1, 1000),
        "overrun_warning_interval_s": (0.1, 86400.0),
        "busy_wait_s": (0.0, 1.0),
    }

    def __post_init__(self) -> None:
        super().__post_init__()
        require(
            self.max_input_age_s is None or self.period_s <= self.max_input_age_s,
            "max_input_age_s must be >= period_s",
        )
        require(0 <= self.busy_wait_s < self.period_s, "busy_wait_s must be in 0..period_s")

    @property
    def input_age_limit_s(self) -> float:
        """The output gate's age limit: ``max_input_age_s``, by default ``stale_after_s``, the
        age at which the validator calls a reading stale (one notion of fresh). Two periods,
        the default before, gated 15.6 % of the frames on a 2-core machine at load 0.8 and
        22.9 % with both cores busy (every cycle started 1 ms late); 10 ms, 0.02 % and
        0.16 %: a robot stopped for nothing. A stall of 20 ms is still stopped by age."""
        return self.stale_after_s if self.max_input_age_s is None else self.max_input_age_s

    @property
    def clock_lag_bound_s(self) -> float:
        """The longest before its read a PLC sample the gateway uses can have been made:
        ``heartbeat_timeout_s`` (the longest the PLC can hold its newest sample with the
        watchdog armed) + ``input_age_limit_s`` (the oldest a reply may be). A counting
        heartbeat may count no more PLC time than passed on the gateway's clock since the
        last sample plus this (gateway/runtime/clock.py, docs/security.md)."""
        return self.heartbeat_timeout_s + self.input_age_limit_s


@dataclass(frozen=True)
class TlsConfig:
    """Modbus/TCP Security (TLS); paths to PEM files."""

    certfile: str  # this client's certificate (PEM)
    keyfile: str  # its private key (PEM)
    cafile: str | None = None  # the CA that signed the PLC's certificate; null: the system's
    verify_peer: bool = True  # refuse a PLC whose certificate does not verify


@dataclass(frozen=True)
class ModbusTcpConfig(Ranged):
    host: str = "127.0.0.1"  # the PLC's address
    port: int = 5020  # the PLC's Modbus TCP port (502 on most PLCs)
    unit_id: int = 1  # the Modbus unit (slave) id the PLC answers to
    timeout_s: float = 0.05  # a transaction not answered within this is a timeout
    connect_timeout_s: float = 1.0  # a connection attempt gives up after this
    # read and write in one transaction (function 23); false: functions 3 and 16
    use_fc23: bool = True
    # first wait before reconnecting; it doubles after each failure ...
    reconnect_min_s: float = 0.05
    reconnect_max_s: float = 2.0  # ... up to this
    tls: TlsConfig | None = None
    registers: RegisterMap = field(default_factory=RegisterMap)
    RANGES: ClassVar[Ranges] = {
        "port": (1, 65535),
        "unit_id": (0, 255),
        "timeout_s": (1e-4, 60.0),
        "connect_timeout_s": (1e-3, 600.0),
        "reconnect_min_s": (1e-3, 3600.0),
        "reconnect_max_s": (1e-3, 3600.0),
    }

    def __post_init__(self) -> None:
        super().__post_init__()
        require(
            self.reconnect_min_s <= self.reconnect_max_s,
            "reconnect_min_s must not exceed reconnect_max_s",
        )

    @property
    def endpoint(self) -> str:
        """``modbus_tcp 127.0.0.1:5020 unit 1``: the server's one name in logs and errors."""
        return f"modbus_tcp {self.host}:{self.port} unit {self.unit_id}"


@dataclass(frozen=True)
class CanopenConfig(Ranged):
    interface: str = "virtual"  # python-can interface: socketcan, virtual, udp_multicast, ...
    channel: str = "cdpr"  # its channel, e.g. can0
    bitrate: int = 1_000_000  # the bus bitrate (bit/s)
    gateway_node_id: int = 0x20  # this gateway's CANopen node id
    analog_node_id: int = 0x10  # the analog input module's node id (CiA 401)
    plc_node_id: int = 0x01  # the PLC's node id (NMT master, setpoints)
    sync_period_s: float = 0.001  # the master's SYNC period: one cycle per SYNC
    timeout_s: float | None = None  # read timeout; default 2.5 SYNC periods
    gateway_eds: str = "gateway.eds"  # relative: beside the config file (left out: shipped)
    # EDS of the analog module (relative: beside the config file)
    analog_eds: str = "analog_in_401.eds"
    plc_eds: str = "plc_master.eds"  # EDS of the PLC master (relative: beside the config file)
    RANGES: ClassVar[Ranges] = {
        "bitrate": (10_000, 1_000_000),
        "gateway_node_id": (1, 127),
        "analog_node_id": (1, 127),
        "plc_node_id": (1, 127),
        "sync_period_s": (1e-4, 1.0),
        "timeout_s": (1e-4, 10.0),
    }

    def __post_init__(self) -> None:
        super().__post_init__()
        ids = {self.gateway_node_id, self.analog_node_id, self.plc_node_id}
        require(len(ids) == 3, "gateway_node_id, analog_node_id and plc_node_id must differ")

    @property
    def endpoint(self) -> str:
        """``canopen virtual:cdpr node 32``: the gateway's node in logs and errors."""
        return f"canopen {self.interface}:{self.channel} node {self.gateway_node_id}"


@dataclass(frozen=True)
class BusConfig:
    # modbus_tcp, canopen or virtual (in process, for tests and demo --offline)
    driver: str = "modbus_tcp"
    modbus_tcp: ModbusTcpConfig = field(default_factory=ModbusTcpConfig)
    canopen: CanopenConfig = field(default_factory=CanopenConfig)


@dataclass(frozen=True)
class MetricsConfig(Ranged):
    enabled: bool = True  # serve /metrics for Prometheus
    # the address it listens on (loopback unless a scraper elsewhere needs it)
    host: str = "127.0.0.1"
    port: int = 9109  # 0: any free port
    certfile: str | None = None  # serve HTTPS with this certificate (PEM) ...
    keyfile: str | None = None  # ... and this key
    basic_auth_user: str | None = None  # require HTTP basic auth with this user ...
    # ... and the password whose SHA-256 (hex) this is
    basic_auth_password_sha256: str | None = None
    RANGES: ClassVar[Ranges] = {"port": (0, 65535)}


@dataclass(frozen=True)
class LimitsConfig(Ranged):
    """Plausibility bounds of the PLC's setpoints (gateway/runtime/plausibility.py).

    The pose must lie in the frame's bounding box widened by ``workspace_margin_m``, with
    rotations up to ``max_rotation_rad``; cable speeds up to ``max_cable_speed_m_s``.
    """

    max_cable_speed_m_s: float = 10.0  # a setpoint cable speed above this flags that channel
    max_rotation_rad: float = math.pi  # a pose rotated further flags every channel
    # a pose outside the frame's box widened by this flags every channel
    workspace_margin_m: float = 0.5
    RANGES: ClassVar[Ranges] = {
        "max_cable_speed_m_s": (1e-6, 100.0),
        "max_rotation_rad": (1e-6, TWO_PI),
        "workspace_margin_m": (0.0, 100.0),
    }


RECORD_KINDS = (
    "velocity",
    "tension_sensor",
    "length",
    "pose",
    "mass",
    "tension_corrected",
    "status",
)


@dataclass(frozen=True)
class RecordConfig(Ranged):
    """The ``record:`` config section; ``path`` None: no recording unless ``--record``."""

    # record what the gateway sees to this file (.csv, .csv.gz, .parquet) or folder
    path: str | None = None
    rotate_bytes: int | None = None  # a new file after this many bytes of CSV text
    rotate_s: float | None = None  # a new file after this many seconds
    columns: tuple[str, ...] = RECORD_KINDS  # which kinds of columns to record
    buffer_rows: int = 65536  # ring size: 65 s at 1 kHz of disk stall before drops
    batch_s: float = 0.1  # the writer drains the ring this often
    layout: str = "files"  # or "hive": path is a folder of robot=R/date=D/part-N.parquet
    robot: str | None = None  # the robot's name in the metadata (and the tree); None: host
    RANGES: ClassVar[Ranges] = {
        "rotate_bytes": (4096, 1 << 40),
        "rotate_s": (1.0, 1e7),
        "buffer_rows": (16, 1 << 24),
        "batch_s": (0.001, 10.0),
    }

    def __post_init__(self) -> None:
        super().__post_init__()
        require(self.layout in ("files", "hive"), "layout must be 'files' or 'hive'")
        require(
            self.robot is None
            or re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}", self.robot) is not None,
            "robot must be 1..64 letters, digits, '_', '.', '-' (a folder name of the tree)",
        )
        unknown = [c for c in self.columns if c not in RECORD_KINDS]
        require(not unknown, f"columns: unknown {unknown[:1]} (known: {', '.join(RECORD_KINDS)})")


@dataclass(frozen=True)
class Config:
    geometry: GeometryConfig
    tension: TensionConfig = field(default_factory=TensionConfig)
    sensor: SensorConfig = field(default_factory=SensorConfig)
    friction: FrictionConfig = field(default_factory=FrictionConfig)
    loop: LoopConfig = field(default_factory=LoopConfig)
    bus: BusConfig = field(default_factory=BusConfig)
    metrics: MetricsConfig = field(default_factory=MetricsConfig)
    limits: LimitsConfig = field(default_factory=LimitsConfig)
    record: RecordConfig = field(default_factory=RecordConfig)
    # the soft PLC's plant: trajectory, noise, hidden effects (sim_plc/config.py)
    sim_plc: dict[str, Any] = field(default_factory=dict)
    source: str = field(default="", metadata={"file": False})  # the file's path, not a key

    def __post_init__(self) -> None:
        fr = self.friction
        try:
            _effect_values(fr.effects, self.cables, fr.pulley_radius_m, "effects")
        except ValueError as exc:
            raise ValueError(f"friction: {exc}") from None
        self._check_heartbeat()

    def _check_heartbeat(self) -> None:
        """A counter's modulus must fit the register the heartbeat is read from."""
        hb = self.loop.heartbeat
        if hb.kind != "counter" or hb.modulus is None:
            return
        if self.bus.driver == "modbus_tcp":
            reg = self.bus.modbus_tcp.registers.plc_heartbeat.type
            key = "bus.modbus_tcp.registers.plc_heartbeat"
        else:  # CANopen 2004h and the virtual image: uint16
            reg, key = "uint16", f"the {self.bus.driver} PLC heartbeat"
        values = HEARTBEAT_VALUES.get(reg, FLOAT32_EXACT)
        if hb.modulus > values:
            raise ValueError(
                f"loop.heartbeat.modulus: {hb.modulus} is more than {key} ({reg}) can count "
                f"({values} values)"
            )

    @property
    def cables(self) -> int:
        return self.geometry.cables


def is_loopback_host(host: str) -> bool:
    """True for 127.0.0.0/8, ::1 and localhost: an address no other host can reach."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def exposure_warning(key: str, host: str, port: int, source: str = "") -> str | None:
    """The line to log when ``key`` binds a listener other hosts can reach, else None."""
    if is_loopback_host(host):
        return None
    where = f" in {source}" if source else ""
    return (
        f"{key}{where} binds {host}:{port}: reachable from other hosts, not only this "
        "one (the default is 127.0.0.1); make sure a firewall limits who can connect"
    )


def config_warnings(cfg: Config) -> list[str]:
    """Values that are legal but probably wrong, one line each naming the file and key."""
    where = f"{cfg.source}: " if cfg.source else ""
    lines = []
    if cfg.tension.max_n > cfg.sensor.range_n:
        lines.append(
            f"{where}tension.max_n: {cfg.tension.max_n:g} N is above the sensor range "
            f"(sensor.range_n: {cfg.sensor.range_n:g} N): tensions above the range read as "
            "overflow (invalid)"
        )
    return lines


def output_path(path: str | Path, option: str) -> Path:
    """``path`` for a file a command will write, checked before the work starts.

    The directory must exist and be writable (it is never created: a typo in a path must
    not leave directories behind); errors name the option and the path.
    """
    p = Path(path)
    parent = p.parent
    if not parent.is_dir():
        raise ConfigError(f"{option} {p}: directory {parent} does not exist")
    if p.is_dir():
        raise ConfigError(f"{option} {p}: is a directory")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise ConfigError(f"{option} {p}: directory {parent} is not writable")
    return p


def config_from_mapping(data: dict[str, Any], source: str = "") -> Config:
    """Validate a parsed YAML mapping into a :class:`Config`."""
    if "source" in data:  # 'source' is filled in here, never read from the file
        raise ConfigError(f"{source}: source: unknown key")
    cfg = convert(Config, {**data, "source": source}, "", source)
    stated = (data.get("bus") or {}).get("canopen") or {}
    return _with_eds_resolved(cfg, stated, source if source and Path(source).is_file() else None)


def _with_eds_resolved(cfg: Config, stated: dict[str, Any], config_file: str | None) -> Config:
    """The EDS paths made absolute: a relative path the file states names a file beside the
    config file; one it leaves out is the shipped EDS file of that name (config/)."""
    can = cfg.bus.canopen

    def where(key: str, value: str) -> str:
        return str(resolve_beside(value, config_file if key in stated else None))

    can = dataclasses.replace(
        can,
        gateway_eds=where("gateway_eds", can.gateway_eds),
        analog_eds=where("analog_eds", can.analog_eds),
        plc_eds=where("plc_eds", can.plc_eds),
    )
    return dataclasses.replace(cfg, bus=dataclasses.replace(cfg.bus, canopen=can))


def load_config(path: str | Path = DEFAULT_CONFIG_PATH) -> Config:
    """Read and validate a full config file."""
    return config_from_mapping(read_yaml(path), str(path))


def load_friction(path: str | Path) -> FrictionConfig:
    """Read a nominal model file: a ``friction:`` mapping alone or inside a full config."""
    data = read_yaml(path)
    if "friction" in data:
        return convert(FrictionConfig, data["friction"], "friction", str(path))
    return convert(FrictionConfig, data, "", str(path))
