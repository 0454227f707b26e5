"""The visual search network: where should the agent look for a category? (paper §3.4).
One module per role:

* :mod:`.config`: the options of ``tidee gen search``, ``tidee train search`` and
  ``tidee eval search`` (light: no torch);
* :mod:`.model`: the network and ``VisualSearch``, what the agent runs (runtime);
* :mod:`.data`: map snapshots and ground-truth targets (``tidee gen search``);
* :mod:`.train`: training; :mod:`.eval`: the search benchmark (Table 2) and held-out map metrics;
* :mod:`.commands`: the ``tidee`` commands.

The agent at run time imports ``model`` only. This file imports nothing, so the command line
can read ``config`` without loading torch.
"""
