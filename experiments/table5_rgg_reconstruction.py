"""Table 5: texture reconstruction with vs without the RGG module.

    python experiments/table5_rgg_reconstruction.py --preset small --seeds 0 1 2

Two full Stage I trainings (I-1 + I-2) that differ only in `unet.use_rgg` (without RGG the
decoders use plain skip connections).
"""

from irdepth_experiments.runner import RECON_COLUMNS, Arm, Table, main

TABLE = Table(
    name="table5_rgg_reconstruction",
    title="Table 5: texture reconstruction with vs without RGG",
    about=("Full Stage I (I-1 + soft multi-task I-2) with the radiation-field gradient guidance "
           "module and with plain skip connections (`unet.use_rgg=false`); everything else equal."),
    arms=(Arm("with RGG", "stage1"),
          Arm("without RGG", "stage1", ("unet.use_rgg=false",))),
    columns=RECON_COLUMNS,
    paper={"with RGG": dict(ssim=0.869, psnr=28.481, entropy=7.377),
           "without RGG": dict(ssim=0.837, psnr=27.093, entropy=7.332)},
)

if __name__ == "__main__":
    main(TABLE)
