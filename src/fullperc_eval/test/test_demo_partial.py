"""``supervisor demo`` stopped with Ctrl-C: the bag holds part of the task, so no MAE table is printed for it.

The installed ``supervisor`` runs a stand-in graph (``demo --graph``): a recorder that writes a real bag and closes
it on SIGINT, and a "simulator" whose task never ends. Ctrl-C (SIGINT to the supervisor, as a terminal sends it)
must stop the graph, leave the bag closed, and end with a message that calls the bag partial and names the
command that evaluates it anyway -- not a Table 1 that looks like the task's result.
"""

from __future__ import annotations

import os
import signal
import sys
import textwrap

from fullperc_common.testing import installed_exe, wait_for
from fullperc_eval.bag.errors import BagError
from fullperc_eval.bag.metadata import load_metadata
from fullperc_eval.bag.reader import BagReader

# SIGINT sets a flag the loop polls, as bag/record.py does: a KeyboardInterrupt raised inside write_msg (likelier on
# a busy machine) would leave half a record in the file before close() writes the footer.
RECORDER = textwrap.dedent("""
    import signal, sys, time
    from fullperc_eval.bag.writer import BagWriter
    stop = []
    signal.signal(signal.SIGINT, lambda *a: stop.append(1))
    w = BagWriter(sys.argv[1], flush_interval=0.1).open()
    w.add_topic("/a", "std_msgs/msg/String")
    String = w.typestore.types["std_msgs/msg/String"]
    print("Recording to", sys.argv[1], flush=True)
    i = 0
    try:
        while not stop:
            w.write_msg("/a", time.time_ns(), String(data=str(i)))
            i += 1
            time.sleep(0.01)
    finally:
        w.close()
""")


def test_ctrl_c_does_not_evaluate_the_partial_bag(procs, tmp_path):
    rec = tmp_path / "rec.py"
    rec.write_text(RECORDER)
    graph = tmp_path / "graph.yaml"
    graph.write_text(textwrap.dedent(f"""
        name: partial_demo
        grace: 10
        processes:
          - name: record
            cmd: [{sys.executable}, {rec}, "{{out}}/bag"]
            ready: {{log: "Recording to"}}
          - name: sim
            cmd: [{sys.executable}, -c, "import signal, sys, time; signal.signal(signal.SIGINT, lambda *a: sys.exit(0));
                  print('task started', flush=True); time.sleep(600)"]
            ready: {{log: "task started"}}
            ends_graph: true
        """))
    out = tmp_path / "out"
    p = procs.start([installed_exe("fullperc_eval", "supervisor"), "demo", "--graph", str(graph), "--task", "T-1",
                     "--out", str(out)], name="demo")
    wait_for(lambda: "[sim] task started" in procs.log(p) or p.poll() is not None, timeout=120,
             what="the graph to start")
    assert p.poll() is None, procs.log(p)
    (run_dir,) = out.iterdir()
    bag = run_dir / "bag"

    def flushed() -> int:
        try:
            return int(load_metadata(bag)["message_count"])
        except BagError:
            return 0

    wait_for(lambda: flushed() > 0, timeout=60, what="the recorder's first flush")

    os.kill(p.pid, signal.SIGINT)  # what Ctrl-C in the terminal sends to the supervisor
    wait_for(lambda: p.poll() is not None, timeout=120, what="the demo to exit")
    log = procs.log(p)
    assert p.returncode == 130, log
    assert "all processes stopped: sim=" in log and "record=0" in log, log
    assert "Traceback" not in log, log
    assert "interrupted (SIGINT)" in log and "PARTIAL" in log, log
    assert f"evaluate {bag}" in log, log
    assert "Table 1" not in log and "MAE" not in log, log
    assert not (run_dir / "report").exists()
    with BagReader(bag) as r:  # the recorder was stopped cleanly: a complete bag
        assert r.message_count > 0 and sum(1 for _ in r.messages()) == r.message_count
