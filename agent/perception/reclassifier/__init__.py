"""The crop reclassifier, the detector's second stage, one module per role: ``config`` (its
options; light), ``model`` (the network, crops and fusion: the agent's runtime), ``train``
(``tidee train reclassifier``).

Nothing is imported here, so that importing ``config`` stays light."""
