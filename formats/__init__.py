"""The contracts between the parts of skinlayers: what crosses from one part to another, defined once.

Imports nothing of the project; every part (model, acquire, calibration, reconstruct) imports from here.

| module | what it defines | written by | read by |
|---|---|---|---|
| ``cube`` | the reflectance cube ``cube.exr`` and its typed header | calibration | reconstruct |
| ``maps`` | parameter maps ``maps.exr``, interface absorbance ``ink.exr`` | reconstruct, acquire (truth), the user | model's renderer |
| ``exr`` | OpenEXR I/O and the spectral image format | every part | every part |
| ``manifest`` | a session folder's ``manifest.json`` | acquire | calibration |
| ``rig`` | the rig a session records (bands, filters, camera, targets) | acquire | calibration |
| ``settings`` | the strict settings base, the one YAML loader and override rule | — | every part's settings |
| ``errors`` | the base of every error a user can cause | — | the command line |
| ``files`` | atomic writes, checksums, safe file names | — | every writer |
| ``version`` | the software version every output records | — | every writer |
"""
