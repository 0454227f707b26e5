"""Memex + rGCN: where does a picked-up object belong? (paper §3.3). One module per role:

* :mod:`.config`: the options of the network, ``tidee train rgcn``, ``tidee eval placement``
  and ``tidee eval ceiling`` (light: no torch);
* :mod:`.memex`: scene graphs and the Memex (runtime: no torch, no simulator);
* :mod:`.model`: the network and ``RGCNPlacement``, the agent's placement model (runtime);
* :mod:`.data`: tidy rooms from the simulator as the Memex and as samples;
* :mod:`.train`, :mod:`.eval`: training and ``tidee eval placement``;
* :mod:`.commands`: the ``tidee`` commands.

The agent at run time imports ``memex`` and ``model`` only. This file imports nothing, so the
command line can read ``config`` without loading torch.
"""
