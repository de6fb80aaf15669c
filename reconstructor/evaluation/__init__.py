"""The paper's evaluation: methods and baselines (``methods.py``, ``baselines.py``), scores that
only evaluation reports (``metrics.py``, ``lpips.py``, ``temporal.py``), the protocols' plan
(``plan.py``), running one job (``runner.py``) and a whole plan (``run.py``), tables and pictures
(``tables.py``), the report (``doc.py``), the held-out scores of ``egosurg reconstruct
--evaluate`` (``held_out.py``), and the ``egosurg evaluate`` command (``cli.py``).

May import anything in the reconstructor. Nothing outside evaluation/ imports it, except the
command modules (``reconstructor.cli``) that run it: training never depends on how it is judged.
"""
