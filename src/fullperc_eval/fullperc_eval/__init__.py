"""Evaluation: OR digital twin, device emulators, rosbag2 record/replay, offline evaluation, supervisor."""
