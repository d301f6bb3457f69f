"""Table 7: depth with vs without the sky loss.

    python experiments/table7_sky_loss.py --preset small --seeds 0 1 2

Two Stage II trainings on the HSV pseudo-RGB that differ only in `stage2.sky_loss` (the sky
loss pulls predictions in the Stage I sky mask to 0.99 x the largest training depth), and the
blank-image control (a constant grey input, with the sky loss).
"""

from irdepth_experiments.runner import DEPTH_COLUMNS, SKY_COLUMNS, Arm, Table, main

TABLE = Table(
    name="table7_sky_loss",
    title="Table 7: depth with vs without the sky loss",
    about=("Stage II on the HSV pseudo-RGB with SiLog + lambda_sky x sky loss and with SiLog "
           "alone (`stage2.sky_loss=false`). The depth metrics count only pixels with "
           "ground-truth depth, which never include the sky; beside them, on the labelled "
           "evaluation frames: the share of true-sky pixels predicted at >= 0.9 x the sky "
           "reference depth, and AbsRel within 3 px of the skyline. Control: *blank* = the same "
           "training with the sky loss on a constant grey image."),
    arms=(Arm("without sky loss", "stage2", ("stage2.sky_loss=false",)),
          Arm("with sky loss", "stage2"),
          Arm("blank (control)", "stage2", ("stage2.preprocessing=blank",))),
    columns=DEPTH_COLUMNS + SKY_COLUMNS,
    paper={"without sky loss": dict(d1=0.964, d2=0.987, d3=0.996, abs_rel=0.060, sq_rel=0.482,
                                    rmse=3.805),
           "with sky loss": dict(d1=0.967, d2=0.989, d3=0.996, abs_rel=0.054, sq_rel=0.436,
                                 rmse=3.705)},
)

if __name__ == "__main__":
    main(TABLE)
