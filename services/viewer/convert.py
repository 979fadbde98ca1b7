"""A recording converted to Rerun offline (``artrack view IN.mcap OUT.rrd``), drawn as the live viewer draws.

The MCAP file is read front to back with the recorder's damage-tolerant reader
(``services.recorder.reading.Scan``), in file order (the order messages reached the
recorder); each payload is decoded with ``protocol.decode`` and logged through the same
``Scene`` and ``ViewLog`` as the viewer node. Images go in at full rate unless
``options.image_hz`` limits them. Payloads that do not decode (channels recorded raw,
unknown schemas) are counted and skipped. A damaged file is converted up to its damage,
which ``Conversion.damage`` then describes.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from services.recorder.reading import Damage, Scan
from services.viewer.recording import ViewLog, open_recording
from services.viewer.scene import Scene, ViewOptions


@dataclass
class Conversion:
    """What a conversion read and wrote."""

    messages: int = 0
    rows: int = 0
    undecodable: int = 0
    damage: Damage | None = None


def convert(source: Path, target: Path, options: ViewOptions) -> Conversion:
    """Write ``target`` (.rrd) from the recording ``source`` (.mcap); NotMcap before anything is written."""
    scan = Scan(source)
    done = Conversion()
    with ViewLog(open_recording(source.name, out=target, recording_id=source.stem), Scene(options)) as view:
        for _, message in scan.decoded():
            view.log(message)
        done.rows = view.rows
    done.messages, done.undecodable, done.damage = scan.read, scan.undecodable, scan.damage
    return done
