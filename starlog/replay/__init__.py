"""What the stages share to replay a log: the machinery between a stage's algorithm and its input and output.

- :mod:`~starlog.replay.layer`: open the input, write the stage's layer on it (:func:`~starlog.replay.layer.extend_log`,
  :class:`~starlog.replay.layer.StageOutput`) and record its provenance;
- :mod:`~starlog.replay.window`: ``--start`` / ``--end``, a stage run on a window of its input;
- :mod:`~starlog.replay.channels`: the track channels a stage reads, and the check that it read every message;
- :mod:`~starlog.replay.blocks`: a channel cut into blocks of whole chunks, each read by a worker itself;
- :mod:`~starlog.replay.pool`: an ordered map over worker processes that never outlive their owner
  (:mod:`~starlog.replay.lifeline`);
- :mod:`~starlog.replay.spool`: blocks of arrays spooled to a file, for a second pass without a second decode;
- :mod:`~starlog.replay.progress`: progress bars;
- :mod:`~starlog.replay.declaration` and :mod:`~starlog.replay.plugins`: declaring your own stage and finding the
  declared ones (users import both through :mod:`starlog.stage_api`).

It imports no stage: the stages (:mod:`starlog.stages`), ``run`` (:mod:`starlog.pipeline`) and ``live``
(:mod:`starlog.live`) import it. This package imports nothing itself, so the CLI's start-up, which needs the
lifeline, pays for no more.
"""
