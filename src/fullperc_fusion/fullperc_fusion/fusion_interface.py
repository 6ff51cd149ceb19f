"""fusion_node's face to the ROS graph as parameters and names: topic names, frame names, QoS, optional outputs.

Why its own module: these rows say how the node is *wired* (which names, which QoS, which optional topics), not what
it estimates; the offline evaluator reads them with the rest of the table (:data:`fusion_config.PARAMS` includes
:data:`INTERFACE_PARAMS`) but never uses them. ROS-free: the node resolves the names and builds the QoS profiles
(:mod:`fusion_endpoints`).

Names (issue 39, fusion.md §8.3). Every topic is *relative*: :func:`output_topic` gives ``fullperc/<target>/pose``
..., the sources' prefixes are ``omc`` / ``ots`` (:mod:`.pipeline.sources`), so the default namespace keeps the
``/fullperc/...``, ``/omc/...`` names and ``-r __ns:=/or1`` moves every input and output to ``/or1/...``; ``/tf``,
``/tf_static`` and ``/diagnostics`` stay global (tf2's and diagnostic_aggregator's convention). Two ORs on one DDS
domain then share one TF tree, so their frames must differ too: ``frames.base`` / ``frames.omc`` / ``frames.ots`` /
``frames.diana_base`` name the node's frames (defaults ``base``, ``omc``, ``ots``, ``diana_base``), and
``<target>.frame`` a target's child frame on /tf (default: the target's name). Every ``header.frame_id`` the node
writes and every /tf(/_static) transform use them (:class:`Frames`).

QoS: ``qos_reliability`` is the *subscriptions'* reliability. Its default ``auto`` subscribes reliable -- with the
usual reliable drivers DDS re-sends what a busy node's reader missed (best effort lost 4-7 % of a demo's samples under
the test suite's load) -- and when a best-effort publisher (a driver on the sensor-data profile) appears on an input,
the incompatible-QoS event remakes that one subscription best effort, which every publisher matches, with a WARN
(:mod:`fusion_endpoints`). ``best_effort`` starts that way, ``reliable`` never switches (a best-effort publisher is then
only a WARN). Publishers are reliable (a reliable writer matches both kinds of reader). Every topic publisher and
subscription of the node also takes rclpy's ``qos_overrides.<resolved topic>.<publisher|subscription>.<history|depth|
reliability>`` parameters (read-only, set at start); an explicit reliability override is never switched.
"""

from __future__ import annotations

from dataclasses import dataclass

from fullperc_fusion.pipeline.param_table import COUNT, NONEMPTY, NONNEGATIVE, Param, one_of

RELIABILITIES = ("auto", "best_effort", "reliable")
INPUTS = ("per_body", "frames")

INTERFACE_PARAMS: tuple[Param, ...] = (
    Param("publish_final", True, "bool", None, "", "",
          "arrival: publish fullperc/<target>/final, the primary filter's estimates once final (= offline)"),
    Param("publish_velocity", False, "bool", None, "", "",
          "publish fullperc/<target>/velocity (TwistWithCovarianceStamped, frames.base) from the primary filter"),
    Param("publish_poses", True, "bool", None, "", "",
          "publish fullperc/poses (FusedPoseArray, frames.base): every target's newest fused pose and covariance of "
          "the primary filter, one message per wake-up, while a subscriber is matched"),
    Param("status_rate", 0.0, "float", *NONNEGATIVE, "Hz",
          "most FusionStatus messages per second per target and filter, by fused stamp (0 = one per fused output); "
          "an output flagged as a hop, or whose link_bumped changed, always goes out"),
    Param("inputs", "per_body", "str", *one_of(INPUTS), "",
          "what the node subscribes of each source: per_body = <prefix>/<body>/pose and /quality (any driver); "
          "frames = <prefix>/bodies (TrackedBodies: every body of one device frame in one message, as fullperc's "
          "drivers publish it), one message per device frame instead of two per body: less CPU"),
    Param("qos_reliability", "auto", "str", *one_of(RELIABILITIES, "auto, best_effort or reliable"), "",
          "reliability of the input subscriptions: auto = reliable, remade best effort (WARN) when a best-effort "
          "publisher appears on the topic; best_effort matches every publisher but misses are not repaired; reliable "
          "matches reliable publishers only"),
    Param("qos_depth", 2000, "int", *COUNT, "messages",
          "QoS history depth of inputs and outputs: > 3 s at 400 Hz, so a node stalled for seconds loses nothing"),
    Param("tf.enabled", True, "bool", None, "", "",
          "broadcast /tf (base -> <target>) and /tf_static (omc -> base, base -> ots, base -> diana_base)"),
    Param("tf.rate", 0.0, "float", *NONNEGATIVE, "Hz",
          "most /tf transforms per second per target, by fused stamp (0 = one per fused output of the primary filter)"),
    Param("tf.diana_base", None, "pose7", None, "", "m, quaternion x y z w",
          "optional T_base_diana_base (the arm's base in base) for /tf_static [x y z qx qy qz qw]"),
    Param("frames.base", "base", "str", *NONEMPTY, "", "frame of every output (the reference marker)"),
    Param("frames.omc", "omc", "str", *NONEMPTY, "", "the OMC's frame: parent of base on /tf_static"),
    Param("frames.ots", "ots", "str", *NONEMPTY, "", "the OTS's frame: child of base on /tf_static"),
    Param("frames.diana_base", "diana_base", "str", *NONEMPTY, "", "the arm's base frame (tf.diana_base)"),
)
"""The node-wide interface rows; a target's child frame is the per-target row ``<target>.frame``."""

TARGET_FRAME = Param("frame", None, "str", *NONEMPTY, "",
                     "child frame of the target on /tf (default: the target's name)")


@dataclass(frozen=True)
class Frames:
    """The frame names of one node: ``base`` (every output), ``omc``, ``ots``, ``diana_base`` and per target its child
    frame (``targets``)."""

    base: str = "base"
    omc: str = "omc"
    ots: str = "ots"
    diana_base: str = "diana_base"
    targets: tuple[tuple[str, str], ...] = ()

    def of(self, target: str) -> str:
        """The child frame of ``target`` on /tf (its name unless ``<target>.frame`` says otherwise)."""
        return dict(self.targets).get(target, target)


def frames_of(vals: dict) -> Frames:
    """The :class:`Frames` of the node's parameter values (``frames.*``, ``<target>.frame``; defaults for missing)."""
    d = Frames()
    return Frames(vals.get("frames.base", d.base), vals.get("frames.omc", d.omc), vals.get("frames.ots", d.ots),
                  vals.get("frames.diana_base", d.diana_base),
                  tuple((t, vals.get(f"{t}.frame") or t) for t in vals.get("targets", ())))


POSES_TOPIC = "fullperc/poses"
"""The relative name of the poses array (``publish_poses``): every target's newest fused pose per wake-up."""


def input_topic(prefix: str, body: str, what: str, inputs: str = "per_body") -> str:
    """The relative name of the input topic of a source (``prefix``) for ``body``'s ``what`` (pose | quality):
    ``<prefix>/<body>/<what>``, or with ``inputs: frames`` the source's one ``<prefix>/bodies`` (TrackedBodies)."""
    return f"{prefix.rstrip('/')}/bodies" if inputs == "frames" else f"{prefix.rstrip('/')}/{body}/{what}"


def output_topic(target: str, what: str, filter: str = "") -> str:
    """The relative name of an output topic: ``fullperc/<target>/<what>``, a side-by-side filter's
    ``fullperc/<target>/<filter>/<what>``."""
    return f"fullperc/{target}/{filter}/{what}" if filter else f"fullperc/{target}/{what}"
