"""Names and defaults of the evaluation options, without the evaluation's imports.

``recon evaluate`` and ``recon compare`` build their parsers from these (every ``recon``
command, even ``recon --help``, builds every parser), while trimesh, SciPy's k-d tree and
the renderer are imported only when an evaluation runs. The evaluation modules take their
defaults from here: one home per value.
"""
PROTOCOLS = ("exact", "reference")      # recon.evaluation: exact, or the reference's definitions
N_SURFACE_SAMPLES = 20_000              # surface samples per mesh for Chamfer and normals
N_VOLUME_SAMPLES = 50_000               # the reference protocol's GT volume samples
MAPPINGS = ("reference", "centre")      # the reference protocol's mesh vertex mappings
REFERENCE_VIEW_SETS = ("paper", "released")   # the reference protocol's camera sets
