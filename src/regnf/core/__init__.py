"""What every layer shares, at the bottom of the package: atomic writes
(:mod:`~regnf.core.atomic_io`), folder locks (:mod:`~regnf.core.file_lock`), output folders that
lose nothing (:mod:`~regnf.core.output_dir`), process-pool and Ray executors
(:mod:`~regnf.core.executors`), the checks a command makes before it starts
(:mod:`~regnf.core.preflight`), the allocator setting a command trains with
(:mod:`~regnf.core.allocator`), work on one CPU thread for repeatable results and independent
calls side by side (:mod:`~regnf.core.threads`) and lazily loaded package exports
(:mod:`~regnf.core.lazy_exports`). Nothing here imports another part of regnf.
"""
