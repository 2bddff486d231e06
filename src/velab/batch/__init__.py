"""``velab fit`` over many runs: through the fit service (velab.fitservice) -- this process, local fit
processes or a Dask cluster -- the client writing every fit.

* :mod:`velab.batch.address` checks a ``--scheduler`` address (standard library only: the
  CLI parser uses it while ``velab --help`` builds);
* :mod:`velab.batch.local` says how many local processes ``--jobs`` gives;
* :mod:`velab.batch.task` turns one run's finished fit into an *outcome* (plain data, a named reason
  for a failure);
* :mod:`velab.batch.runner` submits one FitRequest per run to the fit service, tries a run once more
  whose process died, saves each fit into its run, one file at a time, from the client only (atomic
  ``save_fit``), and :mod:`velab.batch.report` prints the table, the failures and the JSON document,
  and picks the exit code.
"""
