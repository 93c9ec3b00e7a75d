#!/usr/bin/env python3
"""Signatures in a chaos_soak log (docs/chaos.md): consecutive original FEEDBACK (the device_bridge's ~100 Hz
mirror; copies and stale ones injected by the soak left out) whose force differs by > 0.6 N, by cause; clamp
reversals; grab edges onto a stale snapshot. Usage: chaos_feedback_pairs.py session.lcmlog"""
import collections, math, struct, sys

f = open(sys.argv[1], 'rb')
seen, prev = set(), None
cls, mx, sig = collections.Counter(), collections.defaultdict(float), collections.Counter()
while True:
    h = f.read(28)
    if len(h) < 28:
        break
    _, _, ts, cl, dl = struct.unpack('>IqqII', h)   # LCM log event: sync, number, utime, channel and data sizes
    ch = f.read(cl)
    if not ch.startswith(b'HAPTREE_FEEDBACK_0'):
        f.seek(dl, 1)
        continue
    d = f.read(dl)
    if len(d) != 124:   # lcmt_feedback schema 3; the soak's cut/extended garbage is other sizes
        continue
    _, ut, inst, seq, _, _, ver, sinst, dinst = struct.unpack('>iqqqiqqqq', d[8:72])
    fx = struct.unpack('>3d', d[72:96])
    flags = struct.unpack('>i', d[120:124])[0]
    if d[28:] in seen or abs(ut - ts) > 1e6:   # a copy, or stamped > 1 s away from the log time (stale)
        continue
    seen.add(d[28:])
    n = math.hypot(*fx)
    if prev:
        p = prev
        st = math.dist(fx, p['f'])
        if st > 0.6:
            if inst != p['inst']: c = 'new coupler'
            elif sinst != p['sinst'] and sinst and p['sinst']: c = 'new sim_server'
            elif dinst != p['dinst']: c = 'new device_bridge'
            elif (ver < 0) != (p['ver'] < 0): c = 'grab on/off'
            elif (flags | p['flags']) & 2: c = 'watchdog'
            elif ts - p['t'] > 30000: c = 'mirror gap > 30 ms'
            else: c = 'other (same instances)'
            cls[c] += 1
            mx[c] = max(mx[c], st)
        if inst == p['inst']:
            if p['ver'] < 0 and ver >= 0 and flags & 4:
                sig['grab edge onto a stale snapshot'] += 1
            pn = math.hypot(*p['f'])
            if n > 2.9 and pn > 2.9 and sum(a * b for a, b in zip(fx, p['f'])) < 0 and sinst == p['sinst'] \
                    and not ((flags | p['flags']) & 2):
                sig['clamp reversal, same instances, no watchdog'] += 1
    prev = dict(t=ts, inst=inst, ver=ver, sinst=sinst, dinst=dinst, f=fx, flags=flags)
print('original FEEDBACK', len(seen))
for c, v in cls.most_common():
    print('step > 0.6 N: %s %d (max %.2f N)' % (c, v, mx[c]))
for c, v in sig.items():
    print('%s: %d' % (c, v))
