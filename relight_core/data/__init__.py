"""Synthetic data engine: probes, random scenes, Mitsuba renders, the dataset format and loaders.

Modules: `probes` (bundled + procedural HDR probes), `textures`, `meshes`, `scenes` (random scene
descriptions), `render` (Mitsuba 3), `generate` (the `render-data` driver), `dataset` (on-disk
format + torch Dataset), `mit` (MIT multi-illumination loader), `autolabel`, `cli`.
Nothing is imported here so that `relight_core.data.cli` stays cheap to import.
"""
