"""The accuracy and speed harness: independent-physics simulation (:mod:`.simulate`,
:mod:`.particles`), the voxel baselines (:mod:`.baselines`, :mod:`.tracing`, :mod:`.inr`),
scores (:mod:`.metrics`, :mod:`.evaluation`), the benchmarks (:mod:`.benchmark`,
:mod:`.peer_benchmark`, :mod:`.time_to_accuracy`), sweeps (:mod:`.sweep`) and numerical
stress cases (:mod:`.stress`).  Launches our training through the nerfstudio layer; never
imports the CLI."""
