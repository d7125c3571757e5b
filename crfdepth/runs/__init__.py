"""Running the model over many frames: a folder, a raw drive, a list, a data set to evaluate.

Planning batches (:mod:`crfdepth.runs.batches`: frames read and checked ahead by DataLoader workers, batched by
size), resuming (:mod:`crfdepth.runs.resume`), output files written atomically into locked folders
(:mod:`crfdepth.runs.outputs`), the bookkeeping of bad frames (:mod:`crfdepth.runs.skip_bad`), and several
processes or ranks (:mod:`crfdepth.runs.processes`, :mod:`crfdepth.runs.ranks`, :mod:`crfdepth.runs.launch`);
a folder run (:mod:`crfdepth.runs.folder`) and an evaluation (:mod:`crfdepth.runs.evaluation`) put them together.

Above the API and the data sets, below the command line (docs/design.md section 8): a run takes typed options
(:class:`~crfdepth.runs.folder.FolderRun`, :class:`~crfdepth.runs.evaluation.EvaluationRun`), never an argparse
namespace; its errors are :class:`~crfdepth.errors.InputError` s naming the command's flags, its progress and
report go through callbacks the caller gives. Nothing is imported here, so that importing one module stays
cheap.
"""
