"""qdsearch.store: what a run writes and reads of itself, as data.

Map, imports going down the list only:
- trackers: TensorBoard, W&B and MLflow (--track), offline first, each iteration once;
- metrics: a run's metrics rows;
- archive_data: a run's archive as data (archive.npz: numpy, already a dependency, keeps every
  float64 bit, which a CSV may not, and holds arrays of any shape, a CVT's centroids too), made
  back into its pyribs archive without unpickling; archive.csv of folders from before it;
- saving: a run folder's files, written while the loop goes on (saver threads; on a cluster
  joined by its address, saver processes).
"""
