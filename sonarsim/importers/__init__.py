"""Importers that turn other sonar data layouts into a :class:`sonarsim.dataset.SonarDataset`.

- :mod:`sonarsim.importers.airsas`: the AirSAS rig's LabVIEW CSV folders (docs/importers.md).
- :mod:`sonarsim.importers.pik`: the reference's released ``system_data.pik`` pickles
  (reference code ``data_schemas.py``), read without running any code from the file.
"""
