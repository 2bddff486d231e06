"""``velab fit`` over many runs: local processes or a Dask cluster, the client writing every fit.

The batch is split so that each piece has one job:

* :mod:`velab.batch.address` checks a ``--scheduler`` address (standard library only: the
  CLI parser uses it while ``velab --help`` builds);
* :mod:`velab.batch.task` fits one run read-only and returns the fit as plain data, on
  whatever machine runs it;
* :mod:`velab.batch.local` and :mod:`velab.batch.cluster` run the tasks (local processes;
  a ``distributed`` scheduler, the optional extra ``velab[cluster]``) and yield each
  outcome as it completes;
* :mod:`velab.batch.runner` saves each fit into its run, one file at a time, from the
  client only (atomic ``save_fit``), and :mod:`velab.batch.report` prints the table, the
  failures and the JSON document, and picks the exit code.
"""
