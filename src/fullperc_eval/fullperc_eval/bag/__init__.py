"""rosbag2 bags without rosbag2: message types, QoS, metadata.yaml, writer, reader, recovery, ``record``/``play``.

Layer: the bottom of ``fullperc_eval`` beside :mod:`fullperc_eval.emulators` (neither imports the other); it
imports only ``fullperc_common``/``fullperc_msgs`` and third-party code. Modules:

* :mod:`.errors` -- :class:`BagError`;
* :mod:`.types` -- message type names, definitions and RIHS01 hashes from the ament index, the rosbags
  typestore, the Python class of a type (:func:`~.types.get_message`);
* :mod:`.qos` -- QoS profiles as metadata v9 stores them, and to/from rclpy;
* :mod:`.metadata` -- metadata.yaml (v9) and the topic/file records in it;
* :mod:`.writer` / :mod:`.reader` -- :class:`~.writer.BagWriter` (MCAP or sqlite3), :class:`~.reader.BagReader`;
* :mod:`.recover` -- ``reindex``: rebuild metadata.yaml, make a killed recorder's MCAP complete;
* :mod:`.calibration` -- ``calibration.yaml``, the bag's companion file the evaluator needs;
* :mod:`.record` / :mod:`.play` -- the ``record`` and ``play`` executables (rclpy);
* :mod:`.topic_tools` -- the ``echo``, ``pub`` and ``call`` executables (they share the type lookup);
* :mod:`.cli` -- ``python -m fullperc_eval.bag info|reindex BAG`` (and ``echo|pub|call``).
"""
