"""Table 4: depth under day / dusk / night, IR pipeline vs the same network on RGB images.

    python experiments/table4_illumination.py --preset small --seeds 0 1 2

IR = our pipeline (HSV pseudo-RGB of the raw frame); RGB = the same Stage II training on the
aligned visible image (`stage2.preprocessing=rgb`). Metrics per lighting condition of the test
split. Needs a dataset with aligned RGB images (the synthetic benchmark has them).

Two controls trace what the depth network gets from each input (docs/experiments.md's reading of this
table): 'blank' trains the same Stage II on a constant grey image, so its metrics are what the
scene layout alone gives (no image information); the median-scaled rows are the IR and RGB runs
with each prediction scaled by median(gt) / median(pred), which removes a per-image error of
scale and leaves the error of shape.
"""

from irdepth_experiments.runner import DEPTH_COLUMNS, Arm, Table, main

CONDITIONS = ("day", "dusk", "night")

TABLE = Table(
    name="table4_illumination",
    title="Table 4: depth under different illumination, IR vs RGB",
    about=("The same Stage II training (Depth Anything V2, SiLog + sky loss) on the HSV "
           "pseudo-RGB of the raw LWIR frame (IR, ours) and on the aligned visible image (RGB, "
           "`stage2.preprocessing=rgb`); test metrics per condition. Controls: *blank* = the "
           "same training on a constant grey image (what the scene layout alone gives); "
           "*median-scaled* = the IR / RGB predictions scaled per image by median(gt) / "
           "median(pred) (error of shape without the error of scale)."),
    arms=tuple(Arm(name, "stage2", (f"stage2.preprocessing={pre}",), group=cond)
               for name, pre in (("IR (HSV)", "hsv"), ("RGB", "rgb"), ("blank (control)", "blank"))
               for cond in CONDITIONS)
    + tuple(Arm(f"{name}, median-scaled", "stage2", (f"stage2.preprocessing={pre}",), group=cond,
                metrics="stage2_median")
            for name, pre in (("IR (HSV)", "hsv"), ("RGB", "rgb")) for cond in CONDITIONS),
    columns=DEPTH_COLUMNS,
    paper={"IR (day)": dict(d1=0.974, d2=0.994, d3=0.996, abs_rel=0.041, sq_rel=0.422, rmse=3.018),
           "IR (dusk)": dict(d1=0.963, d2=0.992, d3=0.996, abs_rel=0.048, sq_rel=0.529, rmse=3.351),
           "IR (night)": dict(d1=0.946, d2=0.983, d3=0.993, abs_rel=0.095, sq_rel=0.793,
                              rmse=5.126),
           "RGB (day)": dict(d1=0.976, d2=0.992, d3=0.996, abs_rel=0.039, sq_rel=0.282, rmse=3.503),
           "RGB (dusk)": dict(d1=0.948, d2=0.987, d3=0.995, abs_rel=0.072, sq_rel=0.494,
                              rmse=4.119),
           "RGB (night)": dict(d1=0.909, d2=0.976, d3=0.993, abs_rel=0.086, sq_rel=0.827,
                               rmse=5.266)},
)

if __name__ == "__main__":
    main(TABLE)
