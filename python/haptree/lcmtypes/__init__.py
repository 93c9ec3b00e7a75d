"""haptree's LCM message types, generated at build time by ``lcm-gen -p`` from lcmtypes/*.lcm.

Every generated module ``lcmt_*.py`` in this folder is imported and its class exported under its own
name; ``by_fingerprint`` maps the 8-byte type fingerprint that starts every encoded message to the
class, so a reader needs no table of channel names or hand-written offsets.
"""
import importlib as _importlib
import pathlib as _pathlib

by_fingerprint = {}
__all__ = []
for _path in sorted(_pathlib.Path(__file__).parent.glob("lcmt_*.py")):
    _cls = getattr(_importlib.import_module("." + _path.stem, __name__), _path.stem)
    globals()[_path.stem] = _cls
    by_fingerprint[_cls._get_packed_fingerprint()] = _cls
    __all__.append(_path.stem)
