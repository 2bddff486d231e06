"""velab: water-hammer tests on viscoelastic pipes.

Rig control, HDF5 run files and calibration of the pipe-wall rheology
(spring + m Kelvin-Voigt elements) by the Akaike information criterion.
"""

__version__ = "0.1.0"

from velab.errors import VelabError  # noqa: E402

__all__ = ["VelabError", "__version__", "Recorder", "RecordSettings"]


def __getattr__(name):  # lazy: `import velab` stays light (no numpy/h5py/device layer)
    if name in ("Recorder", "RecordSettings", "RunSummary", "SurgePrediction", "RecorderEvent"):
        from velab import recorder

        return getattr(recorder, name)
    raise AttributeError(f"module 'velab' has no attribute {name!r}")
