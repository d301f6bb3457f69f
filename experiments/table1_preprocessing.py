"""Table 1: 14-bit -> 8-bit pre-processing for depth (HE, CLAHE, camera-like chain, HSV).

    python experiments/table1_preprocessing.py --preset small --seeds 0 1 2

Every row trains the same Stage II (Depth Anything V2, SiLog + sky loss with the sky mask of the
seed's Stage I model) and differs only in the image it sees: the raw frame tone-mapped by
histogram equalisation, CLAHE or the camera-like chain (plateau HE + DDE, our stand-in for the
camera's built-in IRCBA), or our HSV pseudo-RGB. Three more rows say what the HSV image's parts
add: its V channel alone as a grey image (V only), the HSV image with hue 0 everywhere (no
semantics in the input) and a constant grey image (blank: what the scene layout alone gives, the
control every depth verdict must clear, `irdepth_experiments.depth_network`). See `runner.py` for
options and caching.
"""

from irdepth_experiments.runner import DEPTH_COLUMNS, Arm, Table, main

TABLE = Table(
    name="table1_preprocessing",
    title="Table 1: infrared pre-processing for monocular depth",
    about=("Same Stage II training (Depth Anything V2, SiLog + sky loss, same steps and seed) on "
           "four input images: HE, CLAHE, the camera-like chain (plateau HE + DDE; stand-in for "
           "the camera's IRCBA) and the HSV pseudo-RGB of MTSA-UNet (ours); "
           "`cfg.stage2.preprocessing = he | clahe | camera | hsv`. Attribution and control: "
           "*V only* = the HSV image's V channel as grey (`value`), *constant hue* = HSV with hue "
           "0 (`stage2.hue_mode=constant`), *blank* = a constant grey image (`blank`)."),
    arms=(Arm("HE", "stage2", ("stage2.preprocessing=he",)),
          Arm("CLAHE", "stage2", ("stage2.preprocessing=clahe",)),
          Arm("camera-like (IRCBA stand-in)", "stage2", ("stage2.preprocessing=camera",)),
          Arm("HSV (ours)", "stage2", ("stage2.preprocessing=hsv",)),
          Arm("V only", "stage2", ("stage2.preprocessing=value",)),
          Arm("HSV, constant hue", "stage2", ("stage2.preprocessing=hsv", "stage2.hue_mode=constant")),
          Arm("blank (control)", "stage2", ("stage2.preprocessing=blank",))),
    columns=DEPTH_COLUMNS,
    paper={"HE": dict(d1=0.945, d2=0.987, d3=0.996, abs_rel=0.096, sq_rel=0.555, rmse=3.940),
           "CLAHE": dict(d1=0.950, d2=0.986, d3=0.995, abs_rel=0.059, sq_rel=0.534, rmse=3.880),
           "IRCBA (camera)": dict(d1=0.958, d2=0.984, d3=0.993, abs_rel=0.061, sq_rel=0.549,
                                  rmse=3.768),
           "HSV (ours)": dict(d1=0.967, d2=0.989, d3=0.996, abs_rel=0.054, sq_rel=0.436,
                              rmse=3.705)},
)

if __name__ == "__main__":
    main(TABLE)
