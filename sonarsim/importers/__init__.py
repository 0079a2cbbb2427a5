"""Importers that turn other sonar data layouts into a :class:`sonarsim.dataset.SonarDataset`.

- :mod:`sonarsim.importers.airsas`: the AirSAS rig's LabVIEW CSV folders (REFERENCE_SPEC §2.2).
- :mod:`sonarsim.importers.pik`: the reference's released ``system_data.pik`` pickles
  (REFERENCE_SPEC §2.1), read without running any code from the file.
"""
