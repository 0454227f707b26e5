"""The detector evaluations, one module per role: ``config`` (the commands' options; light),
``metrics`` (box AP, in/out-of-place AP: pure numpy), ``eval`` (``tidee eval detector``,
``tidee eval oop``), ``fusion`` (``tidee eval reclassifier``: the alpha/beta sweep),
``report`` (the Markdown reports and example grids) and ``commands`` (``register``).

Nothing is imported here, so that importing ``config`` or ``commands`` stays light."""
