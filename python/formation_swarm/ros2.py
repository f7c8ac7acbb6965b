"""A ROS 2 node without ROS 2: plays robot ``index`` of a swarm started with ``--ros2`` over
rmw_zenoh's wire format, with ``eclipse-zenoh`` and ``rosbags``' ROS 2 type store (both on
PyPI) instead of rclpy. It subscribes to ``/<ns>/robot_<i>/observation``, ``.../odom`` and
``.../scan`` (a ``sensor_msgs/msg/LaserScan``, published when the run's observation model has
the range sensor), answers each observation with a ``geometry_msgs/msg/Twist`` on
``.../cmd_vel`` from a policy (the scripted baseline by default, or a learned actor's checkpoint
played in numpy, ``formation_swarm.NumpyActor``), and announces itself on the
ROS 2 graph with rmw_zenoh's liveliness tokens, as an ``rclpy`` node over ``rmw_zenoh_cpp``
would (docs/ROS2.md).

    python3 -m formation_swarm ros2-node 2 [--endpoint tcp/127.0.0.1:7447] [--namespace formation] [--domain 0]
                                           [--policy models/formation.safetensors]

Every key, type hash and byte here comes from rmw_zenoh's design document and from rosbags, not
from the Rust side, so this node checks the Rust side against sources that are not ours."""

from __future__ import annotations

import hashlib
import queue
import re
import struct
import sys
import threading
import time
from typing import Any, Callable, Optional, Tuple

from .run import FormationError

#: The QoS of every entity's liveliness token: reliable, volatile, keep last 10.
QOS = "::,10:,:,:,,"
#: The rosbags type store the types come from (Jazzy's; the types are the same in Kilted).
STORE = "ROS2_JAZZY"
#: ``layout.dim[1].label`` of an observation: the episode and tick it belongs to.
EPISODE_LABEL = re.compile(r"episode (\d+) tick (\d+)")


def dds_name(ros_type: str) -> str:
    """``geometry_msgs/msg/Twist`` -> ``geometry_msgs::msg::dds_::Twist_``."""
    package, kind, name = ros_type.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def mangle(name: str) -> str:
    """rmw_zenoh's ``mangle_name``: every ``/`` becomes ``%``."""
    return name.replace("/", "%")


def attachment(sequence: int, gid: bytes) -> bytes:
    """rmw_zenoh's attachment: sequence number and source timestamp (ns since the epoch) as
    little-endian int64, the GID's length (16) and the GID."""
    return struct.pack("<qqB", sequence, time.time_ns(), len(gid)) + gid


class Ros2Node:
    """Robot ``index`` as a ROS 2 node named ``robot_<index>_driver`` in ``/<namespace>``.

    ``policy(obs) -> (v, w)`` answers each observation (default: the scripted baseline with
    the Rust defaults' limits, ``formation_swarm.Baseline()``). ``obs`` is every float of the
    robot's observation, the range sensor's rays included (each range / ``scan_range_m``) when
    the model has them; the newest scan in metres is ``latest_scan`` (None in a run without the
    range sensor). A policy with a window of observations (``formation_swarm.NumpyActor``) is
    told more when it has the methods: ``check_observation(model, dim)`` at the first
    observation (it raises ``FormationError`` to refuse the run's model, which ends ``spin``),
    ``reset()`` at each episode's first observation, ``observe(obs)`` for an observation
    superseded before it was answered."""

    def __init__(self, index: int, endpoint: str = "tcp/127.0.0.1:7447", namespace: str = "formation",
                 domain: int = 0, policy: Optional[Callable[[Any], Tuple[float, float]]] = None) -> None:
        try:
            import zenoh
            from rosbags.typesys import Stores, get_typestore
        except ImportError as err:  # pragma: no cover - the message is the point
            raise FormationError(f"ros2-node needs eclipse-zenoh and rosbags (pip install eclipse-zenoh rosbags): {err}")
        from .baseline import Baseline

        self.index, self.domain = index, domain
        self.namespace = namespace.strip("/")
        self.policy = policy if policy is not None else Baseline()
        self.store = get_typestore(getattr(Stores, STORE))
        self.types = self.store.types
        config = zenoh.Config()
        # No shared memory: the node talks TCP to one peer, and a segment zenoh made would
        # outlive a node stopped by a signal in /dev/shm.
        for key, value in [("mode", '"peer"'), ("connect/endpoints", f'["{endpoint}"]'),
                           ("listen/endpoints", "[]"), ("scouting/multicast/enabled", "false"),
                           ("transport/shared_memory/enabled", "false")]:
            config.insert_json5(key, value)
        self.session = zenoh.open(config)
        self.zid = str(self.session.info.zid())
        self.node_name = f"robot_{index}_driver"
        self._tokens = [self.session.liveliness().declare_token(self._token(0, "NN"))]
        self._next_entity = 1
        self._observations: "queue.Queue[Any]" = queue.Queue()
        self.odometry = None
        self.odometry_count = 0
        self.latest_scan = None
        self.scans = 0
        self.twists = 0
        #: The run's observation model (``layout.dim[0].label`` of the first observation).
        self.observation_model: Optional[str] = None
        #: The episode and tick of the newest observation (``layout.dim[1]``), and the episodes seen.
        self.episode: Optional[int] = None
        self.tick: Optional[int] = None
        self.episodes = 0
        self._warned_no_episode = False
        self._lock = threading.Lock()
        self._subscribers = [
            self._subscribe("observation", "std_msgs/msg/Float32MultiArray", self._observations.put),
            self._subscribe("odom", "nav_msgs/msg/Odometry", self._on_odometry),
            self._subscribe("scan", "sensor_msgs/msg/LaserScan", self._on_scan),
        ]
        topic = self.topic("cmd_vel")
        token = self._entity("MP", topic, "geometry_msgs/msg/Twist")
        # rmw_zenoh hashes the token with XXH3-128; any 16 bytes unique to the publisher serve.
        self._gid = hashlib.blake2b(token.encode(), digest_size=16).digest()
        self._cmd_vel = self.session.declare_publisher(self.key(topic, "geometry_msgs/msg/Twist"))
        self._sequence = 0

    # --- names ---------------------------------------------------------------------------

    def topic(self, leaf: str) -> str:
        """``/<namespace>/robot_<index>/<leaf>``."""
        return f"/{self.namespace}/robot_{self.index}/{leaf}"

    def key(self, topic: str, ros_type: str) -> str:
        """``<domain>/<topic>/<DDS type name>/<RIHS01 hash>`` (hash from rosbags)."""
        return f"{self.domain}/{topic.strip('/')}/{dds_name(ros_type)}/{self.store.hash_rihs01(ros_type)}"

    def _token(self, entity: int, kind: str) -> str:
        return (f"@ros2_lv/{self.domain}/{self.zid}/0/{entity}/{kind}/%/{mangle('/' + self.namespace)}/"
                f"{self.node_name}")

    def _entity(self, kind: str, topic: str, ros_type: str) -> str:
        token = (f"{self._token(self._next_entity, kind)}/{mangle(topic)}/{dds_name(ros_type)}/"
                 f"{self.store.hash_rihs01(ros_type)}/{QOS}")
        self._next_entity += 1
        self._tokens.append(self.session.liveliness().declare_token(token))
        return token

    def _subscribe(self, leaf: str, ros_type: str, deliver: Callable[[Any], None]) -> Any:
        topic = self.topic(leaf)
        self._entity("MS", topic, ros_type)

        def on_sample(sample: Any) -> None:
            if sample.attachment is None:
                return  # rmw_zenoh drops samples without its attachment
            deliver(self.store.deserialize_cdr(bytes(sample.payload.to_bytes()), ros_type))

        return self.session.declare_subscriber(self.key(topic, ros_type), on_sample)

    def _on_odometry(self, odometry: Any) -> None:
        with self._lock:
            self.odometry = odometry
            self.odometry_count += 1

    def _on_scan(self, scan: Any) -> None:
        with self._lock:
            self.latest_scan = scan
            self.scans += 1

    # --- the loop -------------------------------------------------------------------------

    def publish(self, v: float, w: float) -> None:
        """One Twist on cmd_vel: linear.x = v, angular.z = w."""
        vector = self.types["geometry_msgs/msg/Vector3"]
        twist = self.types["geometry_msgs/msg/Twist"](linear=vector(x=float(v), y=0.0, z=0.0),
                                                      angular=vector(x=0.0, y=0.0, z=float(w)))
        self._sequence += 1
        payload = bytes(self.store.serialize_cdr(twist, "geometry_msgs/msg/Twist"))
        self._cmd_vel.put(payload, attachment=attachment(self._sequence, self._gid))
        self.twists += 1

    def spin_once(self, timeout: float) -> bool:
        """Waits up to ``timeout`` s for an observation; answers the newest one. True if it did."""
        try:
            batch = [self._observations.get(timeout=timeout)]
        except queue.Empty:
            return False
        while True:
            try:
                batch.append(self._observations.get_nowait())
            except queue.Empty:
                break
        for k, message in enumerate(batch):
            self._follow(message)
            if k + 1 < len(batch) and hasattr(self.policy, "observe"):
                self.policy.observe(message.data)  # superseded, but part of the policy's window
        v, w = self.policy(batch[-1].data)
        self.publish(v, w)
        return True

    def _follow(self, message: Any) -> None:
        """Reads an observation's layout: ``dim[0]`` the run's observation model (checked once by
        a policy with ``check_observation``), ``dim[1]`` ``episode E tick T`` (a policy with
        ``reset`` is reset whenever E changes)."""
        dims = message.layout.dim
        model = dims[0].label if dims else None
        if self.observation_model is None:
            self.observation_model = model
            if hasattr(self.policy, "check_observation"):
                self.policy.check_observation(model, len(message.data))
        match = EPISODE_LABEL.fullmatch(dims[1].label) if len(dims) > 1 else None
        if match is None:
            if not self._warned_no_episode and hasattr(self.policy, "reset"):
                self._warned_no_episode = True
                print(f"robot {self.index}: the observation names no episode (layout.dim[1]; a formation-ros2 "
                      "older than this node): the policy's window is never reset", file=sys.stderr, flush=True)
            return
        episode, self.tick = int(match.group(1)), int(match.group(2))
        if episode != self.episode:
            self.episode = episode
            self.episodes += 1
            if hasattr(self.policy, "reset"):
                self.policy.reset()

    def spin(self, idle_exit: Optional[float] = None) -> None:
        """Answers observations until interrupted (Ctrl-C, SIGTERM) or, with ``idle_exit``, until
        none came for that many seconds after the first."""
        last = None
        while True:
            if self.spin_once(0.1):
                last = time.monotonic()
            elif idle_exit is not None and last is not None and time.monotonic() - last > idle_exit:
                return

    def close(self) -> None:
        """Leaves the graph and closes the session."""
        for token in self._tokens:
            token.undeclare()
        self._tokens = []
        self.session.close()

    def __enter__(self) -> "Ros2Node":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
