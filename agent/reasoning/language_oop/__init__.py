"""The language out-of-place classifier (BERT-OOP, TIDEE §3.2), its fused twin and the
instructions that alter it, one module per role:

* run time (what the agent imports): :mod:`.paragraphs` (what the classifier reads),
  :mod:`.model` (text encoder, heads, classifier, the ``language`` / ``fused`` OOP
  detectors), :mod:`.instructions` (typed preferences);
* data: :mod:`.data` (ground-truth rooms), :mod:`.memory_data` (the agent's own memory),
  :mod:`.frames` (single frames with depth);
* training: :mod:`.train`, :mod:`.fused_train`; evaluation: :mod:`.eval`, :mod:`.instruct_eval`;
* the command line: :mod:`.config` (one dataclass per command) and :mod:`.commands`.

Nothing is re-exported here, so importing a light module of the family loads no torch.
"""
