"""Evaluation: operating-room digital twin, device emulators, rosbag2 record/replay, offline evaluation, process supervisor."""
