"""The RGB-D detector with its OOP head, one module per role: ``config`` (its options; light),
``model`` (the network, target encoding and decoding: the agent's runtime), ``data``
(``tidee gen detection`` frames and loading them), ``train`` (``tidee train detector``).

Nothing is imported here, so that importing ``config`` stays light."""
