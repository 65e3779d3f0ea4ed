"""Training a run: its settings (``config``), the run folder (``run``), the loop
(``trainer``) with its losses and per-image appearance, and the metrics it reports
(``metrics``). docs/training.md."""
