"""``time_align``: the offset between the OMC's and the Vega's stamps from a bag of a moving target, as parameters.

    time_align BAG [--omc-topic /omc/tool/pose] [--ots-topic /ots/tool/pose] [--signal speed|angular|both]
               [--device-latency S] [--transport-delay S] [--out time_offset.yaml | --out -]

Record a few seconds (10-30 s is plenty) of a target both trackers see while you wave it irregularly in the Vega's
volume (``record`` with the two pose topics), then run this on the bag. It estimates how late the Vega's stamps are
relative to the OMC's (:mod:`fullperc_fusion.calibration.time_offset`: speed cross-correlation, sub-sample
least-squares refinement, window scatter for the uncertainty and the drift) and writes a ROS 2 parameters file for
the drivers::

    ros2 run fullperc_drivers ndi_driver --ros-args --params-file ndi_vega.yaml --params-file time_offset.yaml

Sign convention: ``offset_s > 0`` = **OTS stamps late by offset_s relative to OMC**; ``ndi_driver``'s
``device_latency_s`` (subtracted from every Vega stamp) becomes ``--device-latency`` (its value while recording)
``+ offset_s``; if that would be negative, 0, and ``omc_driver``'s ``transport_delay_s`` takes the rest.

Output: a summary on stderr, one JSON line on stdout. Exit 1 with ``error: ...`` for a bag that cannot be read or
a recording that cannot give an offset (too short, too little motion, no clear correlation), never a traceback.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from fullperc_eval.bag.errors import BagError
from fullperc_eval.bag.reader import POSE_TYPE, BagReader, decoded_messages
from fullperc_fusion.calibration.time_offset import SIGNALS, Alignment, AlignmentError, align_tracks

Track = tuple[np.ndarray, np.ndarray, np.ndarray]   # stamps [ns] int64, positions (n, 3) [m], quaternions (n, 4)


def read_tracks(bag: str | Path, omc_topic: str, ots_topic: str) -> tuple[Track, Track]:
    """The two topics' header stamps, positions and orientations (bulk-decoded, :mod:`fullperc_eval.bag.reader`)."""
    with BagReader(bag) as reader:
        for t in (omc_topic, ots_topic):
            if t not in reader.topics:
                have = ", ".join(sorted(x for x in reader.topics if x.endswith("/pose"))) or "none"
                raise BagError(f"bag {str(bag)!r} has no topic {t} (pose topics: {have})")
            if reader.topics[t].msgtype != POSE_TYPE:
                raise BagError(f"bag {str(bag)!r}: topic {t} has type {reader.topics[t].msgtype}, not {POSE_TYPE}")
        msgs = decoded_messages(reader, [omc_topic, ots_topic])
    out = []
    for topic in (omc_topic, ots_topic):
        mine = [m for m in msgs if m.topic == topic]
        out.append((np.array([m.t_ns for m in mine], np.int64), np.array([m.p for m in mine]).reshape(-1, 3),
                    np.array([m.q for m in mine]).reshape(-1, 4)))
    return out[0], out[1]


def align_bag(bag: str | Path, omc_topic: str = "/omc/tool/pose", ots_topic: str = "/ots/tool/pose",
              **kw) -> Alignment:
    """:func:`~fullperc_fusion.calibration.time_offset.align_tracks` on a bag's two pose topics (stamps relative to
    the first one, in s)."""
    (ta, pa, qa), (tb, pb, qb) = read_tracks(bag, omc_topic, ots_topic)
    if not len(ta) or not len(tb):
        raise AlignmentError(f"no messages on {omc_topic if not len(ta) else ots_topic}")
    t0 = int(min(ta[0], tb[0]))
    return align_tracks((ta - t0) * 1e-9, pa, (tb - t0) * 1e-9, pb, qa, qb, **kw)


# ---------------------------------------------------------------------- output: the drivers' parameters, the words
def corrected_parameters(offset_s: float, device_latency_s: float = 0.0,
                         transport_delay_s: float = 0.0) -> dict[str, dict[str, float]]:
    """The driver parameters that remove ``offset_s`` (OTS late by it), given the values used when recording.

    Both parameters are subtracted from their driver's stamps and must be >= 0: ``ndi_driver.device_latency_s``
    takes ``current + offset``; when that would be negative (the Vega's stamps early by more than its current
    latency), it becomes 0 and the rest is subtracted from the OMC's stamps instead (``omc_driver.
    transport_delay_s``), which aligns the two the same way. Only the nodes whose value changes are returned.
    """
    lat = device_latency_s + offset_s
    out: dict[str, dict[str, float]] = {}
    if lat >= 0:
        out["ndi_driver"] = {"device_latency_s": round(lat, 6)}
    else:
        out["ndi_driver"] = {"device_latency_s": 0.0}
        out["omc_driver"] = {"transport_delay_s": round(transport_delay_s - lat, 6)}
    for node, vals in out.items():
        for k, v in vals.items():
            if not 0 <= v < 1:
                raise AlignmentError(f"{node}.{k} would be {v} s (allowed 0 <= value < 1 s): is the offset right?")
    return out


def params_yaml(params: dict[str, dict[str, float]], comment: str) -> str:
    """A ROS 2 parameters file (``--params-file``) setting ``params`` for the nodes in any namespace."""
    lines = [f"# {line}" for line in comment.splitlines()]
    for node, vals in params.items():
        lines += [f"/**/{node}:", "  ros__parameters:"]
        lines += [f"    {k}: {float(v)!r}" for k, v in vals.items()]
    return "\n".join(lines) + "\n"


def describe(offset_s: float) -> str:
    """The offset in words, with its sign spelled out."""
    ms = abs(offset_s) * 1e3
    return f"OTS stamps are {'late' if offset_s >= 0 else 'early'} by {ms:.3f} ms relative to OMC"


def warnings_of(r: Alignment) -> list[str]:
    """What the user should know before trusting the result."""
    w = []
    if r.offset_sigma_s > 0.001:
        w.append(f"uncertainty {r.offset_sigma_s * 1e3:.2f} ms: record longer, with faster and more irregular motion")
    if len(r.windows) < 3:
        w.append(f"only {len(r.windows)} window(s) with motion seen by both: the uncertainty is the fit's own and "
                 "the drift is unknown; record longer")
    if np.isfinite(r.drift) and abs(r.drift) > 3 * r.drift_sigma and abs(r.drift) > 1e-4:
        w.append(f"the offset drifts by {r.drift * 1e6:.0f} ppm ({r.drift * 60e3:.2f} ms per minute): a constant "
                 "parameter cannot correct it (are both drivers mapping device time to the host clock?)")
    if r.signal == "speed" and abs(r.gain - 1) > 0.2:
        w.append(f"the two speeds differ by a factor {r.gain:.2f}: do the OMC body and the NDI tool share their origin "
                 "(else try --signal angular)?")
    return w


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="time_align", description=__doc__.split("\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog="offset_s > 0: OTS stamps are late by offset_s relative to OMC; "
                                        "ndi_driver.device_latency_s := --device-latency + offset_s")
    ap.add_argument("bag", help="rosbag2 bag directory (with metadata.yaml)")
    ap.add_argument("--omc-topic", default="/omc/tool/pose", help="the target as the OMC sees it (default %(default)s)")
    ap.add_argument("--ots-topic", default="/ots/tool/pose", help="the same target as the Vega sees it "
                    "(default %(default)s)")
    ap.add_argument("--signal", choices=SIGNALS, default="speed",
                    help="speed: of the body's origin (default); angular: angular speed (independent of where each "
                         "device puts the origin, noisier); both")
    ap.add_argument("--smooth", type=float, default=0.1, help="derivative filter length [s] (default %(default)s)")
    ap.add_argument("--window", type=float, default=2.0, help="window for the scatter and the drift [s] "
                    "(default %(default)s)")
    ap.add_argument("--max-lag", type=float, default=0.5, help="search range of the offset [s] (default %(default)s)")
    ap.add_argument("--min-corr", type=float, default=0.5, help="least correlation to accept (default %(default)s)")
    ap.add_argument("--device-latency", type=float, default=0.0,
                    help="ndi_driver's device_latency_s while recording [s] (default %(default)s, its default)")
    ap.add_argument("--transport-delay", type=float, default=0.0,
                    help="omc_driver's transport_delay_s while recording [s] (default %(default)s, its default)")
    ap.add_argument("--out", default="time_offset.yaml",
                    help="parameters file to write (default %(default)s; '-': write none)")
    args = ap.parse_args(argv)
    for name in ("smooth", "window", "max_lag"):
        if not getattr(args, name) > 0:
            ap.error(f"--{name.replace('_', '-')} must be > 0")
    try:
        r = align_bag(args.bag, args.omc_topic, args.ots_topic, signal=args.signal, smooth_s=args.smooth,
                      window_s=args.window, max_lag_s=args.max_lag, min_corr=args.min_corr)
        params = corrected_parameters(r.offset_s, args.device_latency, args.transport_delay)
    except (BagError, AlignmentError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    warns = warnings_of(r)
    out = None
    if args.out != "-":
        comment = (f"time_align {args.bag}: {describe(r.offset_s)} (+- {r.offset_sigma_s * 1e3:.3f} ms, 1 sigma; "
                   f"{args.omc_topic} vs {args.ots_topic}, signal {r.signal})\n"
                   f"recorded with ndi_driver.device_latency_s {args.device_latency}, omc_driver.transport_delay_s "
                   f"{args.transport_delay}\nuse: --ros-args --params-file <driver's file> --params-file <this file>")
        out = Path(args.out)
        out.write_text(params_yaml(params, comment))
    print(f"time_align: {describe(r.offset_s)} (+- {r.offset_sigma_s * 1e3:.3f} ms, {len(r.windows)} windows, "
          f"peak correlation {r.peak_corr:.3f})", file=sys.stderr)
    for node, vals in params.items():
        for k, v in vals.items():
            print(f"time_align: {node}.{k} = {v}" + (f" -> {out}" if out else ""), file=sys.stderr)
    for w in warns:
        print(f"warning: {w}", file=sys.stderr)
    doc = {"offset_s": r.offset_s, "offset_sigma_s": r.offset_sigma_s, "meaning": describe(r.offset_s),
           "offset_sigma_windows_s": r.offset_sigma_windows_s, "offset_sigma_fit_s": r.offset_sigma_fit_s,
           "drift": r.drift, "drift_sigma": r.drift_sigma, "windows": len(r.windows),
           "window_offsets_s": [w["offset_s"] for w in r.windows], "peak_corr": r.peak_corr, "gain": r.gain,
           "signal": r.signal, "samples": r.samples, "bag": str(args.bag),
           "topics": {"omc": args.omc_topic, "ots": args.ots_topic}, "params": params,
           "params_file": str(out) if out else None, "warnings": warns}
    print(json.dumps({k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in doc.items()}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
