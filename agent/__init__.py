"""tidee.agent: everything that perceives and decides (paper §3), one folder per stage.

Data flow per step (``runner.py``)::

    Observation --perception/--> Detections --mapping/--> maps + object memory
        --reasoning/ (OOP, placement, relations)--> policy/ (Algorithm 1, skills, navigation/)
        --> Action;  telemetry.py publishes for viewers, evaluation/ scores episodes.
"""
