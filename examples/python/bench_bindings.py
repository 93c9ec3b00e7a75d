"""Per-call cost of a few bindings and of the log reader (thread/process CPU time; docs/python.md).

    PYTHONPATH=build/python /usr/bin/python3 examples/python/bench_bindings.py [LOG]
"""
import sys
import time, statistics, numpy as np, haptree, haptree.lcmlog as L
m = haptree.make_scene("protein_like"); s = haptree.State(m); d = haptree.Data(m)
def per_call(fn, reps=200, rounds=7):
    out = []
    for _ in range(rounds):
        t = time.thread_time()
        for _ in range(reps): fn()
        out.append((time.thread_time() - t) / reps * 1e6)
    return statistics.median(out), statistics.mean(out)
print("forward_dynamics protein_like(857) us/call median/mean: %.1f / %.1f" % per_call(lambda: haptree.forward_dynamics(m, d, s)))
print("State.q view access us/call median/mean: %.3f / %.3f" % per_call(lambda: s.q, reps=20000))
haptree.forward_dynamics(m, d, s)
g = [haptree.make_grab(d, m.nbodies - 1, [0, 0, 0])]
snap = haptree.make_coupling_snapshot(m, d, g); ws = haptree.CouplingWorkspace(snap)
fu = np.zeros((1, 6)); out = np.empty((1, 6))
print("coupling_forces (1 grab, out=) us/call median/mean: %.2f / %.2f" % per_call(lambda: haptree.coupling_forces(snap, fu, ws, out), reps=5000))
LOG = sys.argv[1] if len(sys.argv) > 1 else None
if LOG is None:
    sys.exit(0)
t = time.process_time(); log = L.read(LOG); dt = time.process_time() - t
print("lcmlog.read: %d events in %.2f s CPU (%.0f events/s)" % (log.events, dt, log.events / dt))
t = time.process_time(); fb = log.feedback(); print("feedback frame: %d rows in %.2f s CPU" % (len(fb), time.process_time() - t))
