"""Table 6: semantic segmentation with vs without the RGG module.

    python experiments/table6_rgg_segmentation.py --preset small --seeds 0 1 2

The same two Stage I runs as table 5 (shared through the run cache), read for mIoU.
"""

from irdepth_experiments.runner import SEG_COLUMNS, Table, main
from irdepth_experiments.table5_rgg_reconstruction import TABLE as RECONSTRUCTION

TABLE = Table(
    name="table6_rgg_segmentation",
    title="Table 6: semantic segmentation with vs without RGG",
    about=("mIoU of the full Stage I with RGG and with plain skip connections "
           "(`unet.use_rgg=false`); the same runs as table 5."),
    arms=RECONSTRUCTION.arms,
    columns=SEG_COLUMNS,
    paper={"with RGG": dict(miou=0.6313), "without RGG": dict(miou=0.5988)},
)

if __name__ == "__main__":
    main(TABLE)
