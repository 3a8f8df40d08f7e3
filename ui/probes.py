"""The probe library: bundled HDR probes with thumbnails, and validated probe loading."""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import torch
from PIL import Image

from relight_core import lighting, preview

PROBE_SUFFIXES = (".exr", ".hdr")


@dataclass(frozen=True)
class ProbeEntry:
    """One bundled probe: its name (the file stem), file and thumbnail image."""

    name: str
    path: Path
    thumbnail: Path


class ProbeLibrary:
    """The probes in a folder, their thumbnails (made once into `cache_dir`) and a load cache."""

    def __init__(self, folder: str | Path, cache_dir: str | Path, thumbnail_height: int = 64):
        self.folder = Path(folder)
        self.cache_dir = Path(cache_dir)
        self.cache_dir.mkdir(parents=True, exist_ok=True)
        self.thumbnail_height = thumbnail_height
        self._loaded: OrderedDict[tuple[str, float], torch.Tensor] = OrderedDict()
        self.entries = [self._entry(p) for p in sorted(self.folder.glob("*"))
                        if p.suffix.lower() in PROBE_SUFFIXES]

    @property
    def names(self) -> list[str]:
        """Names of the bundled probes, in gallery order."""
        return [e.name for e in self.entries]

    def path_of(self, name: str) -> Path:
        """The file of a bundled probe, by name."""
        for entry in self.entries:
            if entry.name == name:
                return entry.path
        raise KeyError(name)

    def load(self, path: str | Path) -> torch.Tensor:
        """Load (and cache) a probe file; raises InputError for a bad file."""
        path = Path(path)
        key = (str(path.resolve()), path.stat().st_mtime)
        if key not in self._loaded:
            self._loaded[key] = lighting.load_probe(path)
            while len(self._loaded) > 8:
                self._loaded.popitem(last=False)
        self._loaded.move_to_end(key)
        return self._loaded[key]

    def _entry(self, path: Path) -> ProbeEntry:
        thumbnail = self.cache_dir / f"{path.stem}-{int(path.stat().st_mtime)}.png"
        if not thumbnail.exists():
            image = preview.probe_thumbnail(lighting.load_probe(path), self.thumbnail_height)
            Image.fromarray(image).save(thumbnail)
        return ProbeEntry(path.stem, path, thumbnail)


def probe_choices(library: ProbeLibrary) -> list[tuple[str, str]]:
    """(thumbnail, name) items of the probe gallery; a long name may wrap after its underscores
    (a zero-width space follows each), so every name is shown in full."""
    return [(str(e.thumbnail), e.name.replace("_", "_\u200b")) for e in library.entries]
