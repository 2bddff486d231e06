"""velab: water-hammer tests on viscoelastic pipes.

Rig control, HDF5 run files and calibration of the pipe-wall rheology
(spring + m Kelvin-Voigt elements) by the Akaike information criterion.
"""

from velab.errors import VelabError
from velab.version import __version__

__all__ = ["VelabError", "__version__", "Recorder", "RecordSettings"]
_RECORDING = ("Recorder", "RecordSettings", "RunSummary", "SurgePrediction", "RecorderEvent")


def __getattr__(name):  # lazy for start-up speed only: `import velab` stays light (no numpy/h5py/devices)
    if name in _RECORDING:
        import velab.recording

        return getattr(velab.recording, name)
    raise AttributeError(f"module 'velab' has no attribute {name!r}")
