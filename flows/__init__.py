"""Prefect flows composing the stage tasks: ``bootstrap`` (the loop), one subflow per iteration, ``evaluate`` and
``toy_collection``. Task runners are chosen by configuration (``flows._runners``)."""
