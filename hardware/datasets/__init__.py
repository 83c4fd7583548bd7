"""Importers for public datasets: each opens as a message source (`Dataset`).

    from hardware.datasets import open_dataset, import_to_log

    ds = open_dataset("mrclam", "../shared/data/mrclam_dataset7", robot=1)
    for msg in ds.messages():          # hardware.messages, in timestamp order
        ...
    ds.calibration, ds.metadata["config"]["initial_pose"], ds.metadata["landmarks"]
    import_to_log(ds, "mrclam7_r1.mcap")  # an MCAP trial log that `walkerslam replay` reads

Formats (one module each; `available_formats()`):

    mrclam         hardware.datasets.mrclam         UTIAS MRCLAM folder, one robot
    carmen         hardware.datasets.carmen         CARMEN laser log (GMapping-corrected)
    victoria-park  hardware.datasets.victoria_park  ACFR Victoria Park folder
    mtrx5700       hardware.datasets.mtrx5700       MTRX5700 Player/Stage folder (simulated)

Each module's docstring documents its file format and every conversion decision.
`hardware.datasets.base` has the shared machinery (Dataset, DatasetError, the registry,
the steps every importer takes).
"""

from hardware.datasets.base import (
    FORMATS,
    Dataset,
    DatasetError,
    ImportSummary,
    UnknownNameError,
    available_formats,
    import_dataset,
    import_to_log,
    open_dataset,
)

__all__ = [
    "FORMATS",
    "Dataset",
    "DatasetError",
    "ImportSummary",
    "UnknownNameError",
    "available_formats",
    "import_dataset",
    "import_to_log",
    "open_dataset",
]
