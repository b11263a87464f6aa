"""The workflow's steps as plain functions with typed inputs that return a result object;
the commands (cli/), `demo`, `batch` and the benchmarks call these and print what they
return.

- `track.track(TrackJob) -> TrackResult`: model -> frame source -> camera -> Tracker ->
  smoother -> the pose CSV and its companions (`track.open_job` builds the job the way
  `mirage track` does);
- `build.save_model(BuildResult, ...)`: the model file of `mirage build-model`;
- `calibrate.calibrate_to_file(...) -> Calibration`: the camera file of `mirage calibrate`;
- `report.report(...) -> Report` and `report.write_report`: `mirage report`'s files;
- `campaign`: `mirage batch`'s flights (each a track job and a report).

Nothing here imports click or prints: what people see goes through a `Reporter`
(reporting.py) the caller passes in.
"""
