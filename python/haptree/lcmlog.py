"""Read haptree's LCM logs (lcm-logger, lcm::LogFile) as numpy arrays and pandas frames.

No LCM Python package is needed (Debian 12 ships none). The log container is LCM's documented
format (https://lcm-proj.github.io/lcm/content/log-file-format.html): a sequence of events, each a
28-byte big-endian header -- sync word 0xEDA1DA01, event number (int64), timestamp (int64, µs since
the epoch, when the logger received the message), channel length (int32), data length (int32) --
followed by the channel name and the message bytes. The messages are decoded by the types that
``lcm-gen -p`` generated from lcmtypes/*.lcm at build time (``haptree.lcmtypes``), chosen by the
8-byte type fingerprint that starts every message, so new fields and new message types need no
change here. Messages of unknown types are counted, not decoded.

    import haptree.lcmlog as L
    log = L.read("session.lcmlog", start_s=2.0, end_s=5.0)   # seconds after the first event
    fb = log.feedback()          # one row per HAPTREE_FEEDBACK_<d> message
    fb.groupby("device_id")[["t_s", "force_n_0"]]

Frames flatten each message: scalars are columns, fixed-size arrays ``force_n[3]`` become
``force_n_0..force_n_2``, variable-size arrays stay one object column of numpy arrays. Every frame
has ``t_s`` (log time, seconds after the first event of the file), ``log_utime`` and ``channel``.
"""
import re
import struct

import numpy as np

from . import lcmtypes

SYNC = 0xEDA1DA01
_HEADER = struct.Struct(">IqqII")


class LogFormatError(ValueError):
    """The file is not an LCM log (no sync word where an event must start)."""


def iter_events(path, start_s=None, end_s=None):
    """Yields (eventnum, utime, t_s, channel, data) for every event, in file order.

    t_s is seconds after the file's first event (its receive timestamp).

    start_s / end_s (seconds after the file's first event, either may be None) skip events outside
    [start_s, end_s) without reading their payload. A corrupt region is skipped by scanning for the
    next sync word, as LCM's reader does; a truncated last event ends the iteration.
    """
    with open(path, "rb") as f:
        first = None
        pos = 0
        while True:
            f.seek(pos)
            head = f.read(_HEADER.size)
            if len(head) < _HEADER.size:
                return
            sync, eventnum, utime, chlen, datalen = _HEADER.unpack(head)
            if sync != SYNC:
                if pos == 0:
                    raise LogFormatError(f"{path}: not an LCM log (first 4 bytes 0x{sync:08x}, want 0x{SYNC:08X})")
                nxt = _find_sync(f, pos + 1)
                if nxt < 0:
                    return
                pos = nxt
                continue
            if first is None:
                first = utime
            t = (utime - first) * 1e-6
            end = pos + _HEADER.size + chlen + datalen
            if end_s is not None and t >= end_s:
                return
            if start_s is not None and t < start_s:
                pos = end
                continue
            body = f.read(chlen + datalen)
            if len(body) < chlen + datalen:
                return
            yield eventnum, utime, t, body[:chlen].decode("utf-8", "replace"), body[chlen:]
            pos = end


def _find_sync(f, pos):
    magic = struct.pack(">I", SYNC)
    f.seek(pos)
    carry = b""
    while True:
        chunk = f.read(1 << 16)
        if not chunk:
            return -1
        buf = carry + chunk
        i = buf.find(magic)
        if i >= 0:
            return pos - len(carry) + i
        carry = buf[-3:]
        pos += len(chunk)


def decode(data):
    """The generated-type instance for one message, or None for an unknown type."""
    cls = lcmtypes.by_fingerprint.get(bytes(data[:8]))
    return cls.decode(data) if cls is not None else None


class Log:
    """A decoded log: `messages` is a list of (t_s, log_utime, channel, message) in file order."""

    def __init__(self, path, start_s=None, end_s=None, channels=None):
        self.path = str(path)
        pattern = re.compile(channels) if channels else None
        self.messages = []
        self.undecoded = {}       # channel -> count of messages of unknown type
        self.events = 0
        # t_s counts from the file's first event, with or without a window.
        for _, utime, t, ch, data in iter_events(path, start_s, end_s):
            if pattern is not None and not pattern.fullmatch(ch):
                continue
            self.events += 1
            msg = decode(data)
            if msg is None:
                self.undecoded[ch] = self.undecoded.get(ch, 0) + 1
                continue
            self.messages.append((t, utime, ch, msg))

    def channels(self):
        """{channel: number of decoded messages}."""
        out = {}
        for _, _, ch, _ in self.messages:
            out[ch] = out.get(ch, 0) + 1
        return out

    def of_type(self, type_name):
        return [m for m in self.messages if type(m[3]).__name__ == type_name]

    def frame(self, type_name):
        """pandas.DataFrame of every message of one type (e.g. "lcmt_feedback")."""
        import pandas as pd

        rows = [_flatten(t, u, ch, msg) for t, u, ch, msg in self.of_type(type_name)]
        cls = getattr(lcmtypes, type_name, None)
        if cls is None:
            raise KeyError(f"unknown message type '{type_name}' (known: {', '.join(lcmtypes.__all__)})")
        if not rows:
            return pd.DataFrame(columns=["t_s", "log_utime", "channel"] + list(cls.__slots__))
        return pd.DataFrame(rows)

    # Named frames for the quantities an analysis usually wants.
    def feedback(self):
        """Feedback forces (device units, N): one row per HAPTREE_FEEDBACK_<device> message."""
        return self.frame("lcmt_feedback")

    def device_states(self):
        """Device poses (m, unit quaternion w,x,y,z, m/s, buttons)."""
        return self.frame("lcmt_device_state")

    def user_forces(self):
        """User forces sent to the simulation (scene units, spatial [moment; force] at the grab point)."""
        return self.frame("lcmt_user_force")

    def snapshots(self):
        """Coupling snapshots: version, sim_time, grabs; `ints`/`values` as arrays."""
        return self.frame("lcmt_coupling_snapshot")

    def scene_states(self):
        """Scene states: version, sim_time, active_dofs, neglected_metric, step_ms; body poses as arrays."""
        return self.frame("lcmt_scene_state")

    def stats(self):
        """Process statistics (1 Hz); the free-form extras become columns `extra.<name>`."""
        df = self.frame("lcmt_process_stats")
        if len(df) and "extra_names" in df:
            extras = [dict(zip(n, v)) for n, v in zip(df["extra_names"], df["extra_values"])]
            names = sorted({k for e in extras for k in e})
            for k in names:
                df["extra." + k] = [e.get(k, np.nan) for e in extras]
        return df


def _flatten(t, utime, ch, msg):
    row = {"t_s": t, "log_utime": utime, "channel": ch}
    for name in msg.__slots__:
        v = getattr(msg, name)
        if isinstance(v, (list, tuple)):
            a = np.asarray(v)
            if a.dtype == object or a.ndim == 0:
                row[name] = v
            elif _is_fixed(type(msg), name):
                for i, x in enumerate(a.reshape(-1)):
                    row[f"{name}_{i}"] = x
            else:
                row[name] = a
        elif isinstance(v, bytes):
            row[name] = v
        else:
            row[name] = v
    return row


_fixed_cache = {}


def _is_fixed(cls, name):
    """True when the field's array size is a constant in the .lcm file (its default has that size)."""
    key = (cls, name)
    if key not in _fixed_cache:
        default = getattr(cls(), name)
        _fixed_cache[key] = isinstance(default, list) and len(default) > 0
    return _fixed_cache[key]


def read(path, start_s=None, end_s=None, channels=None):
    """Reads and decodes a log. channels: a regular expression the channel must match fully."""
    return Log(path, start_s=start_s, end_s=end_s, channels=channels)
