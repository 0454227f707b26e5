"""The depth-from-RGB network (the paper's "+est. depth"), one module per role: ``config``
(its options; light), ``model`` (the network and ``DepthEstimator``: the agent's runtime),
``train`` (``tidee train depth``), ``eval`` (``tidee eval depth``).

Nothing is imported here, so that importing ``config`` stays light."""
