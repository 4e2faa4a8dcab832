"""Every size, switch and weight of the Garment Animation NeRF model, in one dataclass.

Defaults are the paper's (Sec. 4 and "Implementation details"; numbers the paper leaves out come
from the authors' code, see ``implementation-notes.md`` Sec. 1). :meth:`ModelConfig.paper` is the
published model; :meth:`ModelConfig.cpu_small` is a reduced model meant to train on a 2-core CPU in
about an hour. A checkpoint stores :meth:`ModelConfig.to_dict`; :meth:`ModelConfig.from_dict`
rejects keys it does not know, so a renamed field fails loudly instead of silently falling back
to a default.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

DETAIL_SELECTION_MODES = ("visibility", "soft_normal")
FIELDS = ("paper", "uvh")
DENSITY_ACTIVATIONS = ("softplus", "trunc_exp")
RADIANCE_ACTIVATIONS = ("softplus", "sigmoid")
#: Where a model's samples go (``ModelConfig.sampler``); the render presets' samplers are the same names.
SAMPLERS = ("box", "shell")
#: How samples are spaced inside the shell (``ModelConfig.shell_spacing``, :class:`~garmentnerf.model.shell_sampler.ShellSampler`).
SHELL_SPACINGS = ("box", "shell")


@dataclass
class ModelConfig:
    """Configuration of the networks, the renderer, the losses and the optimiser schedule; each
    field is documented under it."""

    # ---- Inputs
    history: int = 2
    """k, number of past velocity frames in the velocity map V_t (paper: 2). The dynamic feature encoder E
    then sees 3 (k + 1) channels (normals + k velocities), and 3 more per ``velocity_smoothing`` slot."""
    velocity_smoothing: tuple[float, ...] = ()
    """Time constants (seconds) of smoothed velocity maps E sees after the k velocity maps (not in the paper:
    empty gives its input): each is the causal exponentially weighted mean of the per-frame canonical
    velocities over three time constants (:func:`~garmentnerf.body.surface.smoothed_velocities`), 3 more
    channels each. Two frames of velocity do not say where a skirt's hem has swung: it follows where the
    body has been going for the last fraction of a second. In the sequence occupancy probe (0.1, 0.3 and 1 s)
    it changed nothing over the first 600 steps, which learn the average garment (docs/quality.md, "Telling
    the field where the cloth is"); whether it helps once frames are told apart is not measured."""
    world_normals: bool = False
    """Give E the body's normal map in world space too (3 channels after the others; not in the paper).
    The paper's normals are root-relative, and nothing else E or the field sees says which way the body
    faces, while the scene's lights are fixed in the world: when the character turns, the same cloth
    goes from lit to shaded and the field can only learn the average. On the bundled skirt's training
    camera ``cam00`` the truth's mean garment luminance varies from frame to frame (std 0.018) and C5's
    render does not follow it (std 0.010, correlation -0.18). Measured (recipe WN1, from scratch against
    O1): 0.47 dB of foreground lost on the unseen views, and the render still does not follow the cloth's
    brightness (correlation -0.07; docs/quality.md, "The lights"), so it stays off."""
    frame_code_resolution: int = 0
    """Per-frame codes (not in the paper; 0: none): every training frame gets a learned residual of E's
    output, ``dynamic_encoder_channels x r x r`` at this r, upsampled bilinearly to E's resolution and added
    to F^s_t. A sequence model reaches a frame's own garment shape only through E after many visits of that
    frame (docs/quality.md, "Telling the field where the cloth is"); the code is a per-frame memory that
    learns from each visit at its own rate (``frame_code_lr_scale``). Only the training sequences' frames
    have codes (the run records which, :attr:`frame_codes`); any other motion, or another scene, renders
    without (its F^s_t is E's alone), and so sees what E has learned, not the codes."""
    frame_codes: int = 0
    """Number of per-frame codes: set by the trainer to the frames of the scene's training sequences when
    ``frame_code_resolution`` > 0 (0 in a config written by hand)."""
    frame_code_lr_scale: float = 50.0
    """The per-frame codes learn at ``lr`` times this: each is seen once in about as many steps as there are
    training frames (the sequence occupancy probe: 50 gave +0.07 IoU on the training frames after 600
    steps, 10 +0.01; docs/quality.md). The codes are in Adam with the other weights, which moves each texel
    of a drawn code by about the rate in the sign of its gradient, however small, and whose momentum carries
    the code on for about ten more steps after the visit. Codes trained alone on the bundled C5 (session 19,
    docs/quality.md, "Per-frame codes on the bundled field"): at a rate of 5e-2 they lost 0.65 dB of
    foreground on the held-out cameras (lumpy skirts), at 1.5e-2 they gained 0.31, at 5e-3 0.21. To train
    the codes alone, set ``trained_parameters`` and give ``lr`` the codes' rate with this at 1."""
    frame_code_dropout: float = 0.0
    """Probability that a training step renders its frame without the frame's code (E's output alone;
    0: never). The codes learn each training frame's own garment fast but let E learn less of the rule
    that alone renders a motion it never saw (FC1 lost 0.7 dB of foreground on the held-out motion,
    docs/quality.md, "Per-frame codes"); dropped steps ask E to stand alone. Drawn per image from
    ``(seed, step, rank, image)``, so a resumed run drops the same steps."""
    frame_code_support_margin: int = -1
    """-1 (default): each per-frame code covers the whole atlas. k >= 0: the codes hold values only on the
    texels that the garment's closest body points over the training frames read (their bilinear footprint,
    grown by k texels; :mod:`garmentnerf.model.frame_codes`), and are zero elsewhere, so codes as fine as E's
    output fit a demo's size: the dress's at 128 x 128 with k = 2 hold 35 % of the texels. The trainer
    finds that support when a run starts; it is stored with the weights."""
    info_map_resolution: int = 128
    """Side of the UV info maps N_t, V_t and of the dynamic feature map F^s_t (paper: 128)."""
    image_resolution: int = 512
    """Side of the output image (paper: 512)."""
    reference_resolution: int = 512
    """Side of the front/back reference images of G_img and of the detail feature maps F^d_t made from them by
    G_en (paper: 512, the image size). G_en at this size is the most expensive network on a CPU, hence a
    separate field."""
    feature_image_resolution: int = 128
    """Side of the volume-rendered appearance feature image F^zeta_t, i.e. rays per image side (paper: 128 =
    image / 4). Must be image_resolution divided by 2 ** decoder_upsample_steps."""
    training_crop_density: float = 0.0
    """What one training step renders. 0 (the paper): the whole training camera, resized to ``image_resolution``
    squared. > 0: a window of ``image_resolution`` squared pixels at this many pixels per pixel of the scene's
    camera (1: the scene's own density, e.g. its 512 x 512 images), placed where the character is (its centre
    drawn inside the screen rectangle of the sampling box; see ``train/frames.py``). The same rays per step then
    land on the character at a finer density instead of on background. The renderer reads it back:
    :meth:`training_scale` is the density the model was trained at, which ``quality = 1`` reproduces."""

    # ---- Features
    dynamic_feature_dim: int = 8
    """Channels of F^s_t, the output of E (paper: 8)."""
    detail_feature_dim: int = 8
    """Channels of F^d_t, the output of G_en (paper: 8)."""
    appearance_dim: int = 128
    """zeta, channels of the NeRF appearance feature and of F^zeta_t (paper: 128)."""
    shading_normals: bool = False
    """Give the decoder M_D the body's world-space normal under each pixel (not in the paper): every sample
    carries the posed normal at its closest body point as 3 more channels after zeta, volume-rendered with
    the same weights, so F^zeta has ``appearance_dim + 3`` channels. The scene's lights are fixed in the
    world while everything E and the field see is body-relative, so a field cannot know which side of the
    cloth is lit: across the 16 training cameras of one frame the bundled C5 renders the garment's mean
    luminance with half the truth's contrast (std 0.014 against 0.028 at frame 20, correlation 0.88;
    docs/quality.md, "The lights"). Here the radiance head gets the orientation directly, one conv away.
    Measured (recipe LN1 against O1, from scratch, same images): on the held-out cameras the render's
    brightness follows the truth's (``shading_correlation`` 0.82 against 0.03 for O1's recipe with another
    seed), 0.74 dB more inside the garment, the foreground level (within the 0.55 dB a seed moves); a step
    costs the same. Off by default (not in the paper); the long-run recipe turns it on."""
    depth_normals: bool = False
    """Give the decoder M_D the world-space normal of the rendered surface under each pixel (not in the paper):
    the cross product of the derivatives of the world points the feature image's expected depth puts on its
    rays (``model/depth_normals.py``), 3 channels after the rendered ones. Where ``shading_normals`` gives the
    body's orientation, this is the cloth's own, folds included as far as the density has them; computed
    from the depth without a gradient (it shades, it does not move the geometry). Measured on one frame,
    300 steps (proxy PC4b against PC2b, docs/quality.md, "The garment against a flat colour"): the same
    figures to 0.1 dB, the folds no better placed; off by default."""
    shading_normal_blur: float = 0.0
    """With ``shading_normals``: 0 gives each sample the normal at its closest body point; > 0 (metres) the
    body's normals blurred by a Gaussian of this standard deviation (:mod:`~garmentnerf.model.normal_field`:
    a grid per frame, read trilinearly; the closest point's normal beyond the kernel's reach). Where the cloth
    spans a gap (the skirt across the legs) the closest point is an inner thigh whose normal points
    sideways; blurred, the two thighs cancel and the cloth gets the legs' forward normal (LN1's blotch at
    held02 frame 42, docs/quality.md, "The lights"). Measured (recipe LN2 at 0.05 against LN1, LN1S1): the
    same foreground, 0.3 dB less inside the garment and less shading contrast, the blotch only fainter; so 0."""

    # ---- U-Nets E and G_en (``model/unet.py``)
    encoder_base_width: int = 32
    """Width of the first conv, doubled at every down block (paper: 32, so 32 -> 64/128/256/512)."""
    encoder_depth: int = 4
    """Number of stride-2 down blocks (paper: 4; 128 -> 8x8 bottleneck for E, 512 -> 32x32 for G_en)."""
    encoder_width_scale: float = 1.0
    """Multiplies every U-Net width (paper: 1.0)."""

    # ---- Image generator G_img (``model/image_generator.py``; pre-trained, then frozen)
    neural_texture_channels: int = 16
    """Channels of every neural-texture level and of Q_t (DNG: 16)."""
    neural_texture_levels: int = 4
    """Pyramid levels, each half the previous resolution (DNG: 4)."""
    neural_texture_resolution: int = 512
    """Side of the finest level (DNG: 512 -> 512/256/128/64)."""
    generator_width_scale: float = 1.0
    """Width factor of G_img's encoder-decoder (1.0: the E/G_en widths)."""

    # ---- The field: what a sample is described by and what maps it to density and zeta
    field: str = "paper"
    """``"paper"`` (default): M_NeRF, an MLP on ``[b_o, h, f^d, f^s]`` (``model/nerf_mlp.py``).
    ``"uvh"``: the UV-h field (``model/uvh_field.py``): E emits a per-frame feature volume over
    (u, v, h) (``uvh_slices`` deep), a learned UV-h tri-plane holds what all frames share, the
    sample's offset direction in its skin face's frame tells apart points with the same closest
    body point, and a small MLP (``mlp_depth`` x ``mlp_width``, e.g. 2 x 64) decodes them."""
    uvh_slices: int = 8
    """``uvh`` field: slices of E's per-frame UV-h volume along h (E emits ``dynamic_feature_dim`` times
    this many channels)."""
    uvh_height_range: tuple[float, float] = (-0.1, 0.4)
    """``uvh`` field: the heights h (metres, positive outside the skin) the volume's slices and the
    tri-plane's h axis span; reads beyond take the border value. Default: the generous garment
    band of ``model/height_band.py`` (a skirt's hem swings about 0.35 m from the legs)."""
    uvh_height_freqs: int = 4
    """``uvh`` field: frequencies of the encoding of the normalised h given to the MLP."""
    uvh_canonical_freqs: int = 0
    """``uvh`` field: when > 0, the MLP also gets the sample carried to the canonical body, frequency
    encoded with this many octaves: b_o plus the offset ``x - b_t`` turned from the posed closest face's
    tangent frame into the canonical face's (:func:`~garmentnerf.model.uvh_field.canonical_positions`),
    in the canonical body's box padded by ``uvh_height_range``. The same information as (b_o, h, the
    local direction), laid out as a 3-D point: a one-frame occupancy probe fits the skirt's sheet from
    such a point almost as fast as from posed xyz, and it still follows the body from frame to frame
    (``docs/quality.md``, "A canonical position for the sample"). 0: off (the recipes before it)."""
    uvh_sheet_layers: int = 0
    """``uvh`` field: when > 0, E also emits this many per-frame *sheet heights* g(u, v) (in units of
    0.1 m above the skin, read bilinearly at the sample's UV) and the MLP gets each ``h - g``, frequency
    encoded (``uvh_sheet_freqs``): the garment as a height field over the body per frame, so the
    density can rise and fall within millimetres of the sheet where E's volume has a slice every
    ``(h_max - h_min) / uvh_slices`` (6 cm by default) and its trilinear reads spread the sheet into
    a fog (``docs/quality.md``, "A sheet height per body point"). 0: off (the recipes before it)."""
    uvh_sheet_freqs: int = 6
    """``uvh`` field: frequencies of the encoding of ``h - g`` (normalised like h) per sheet layer."""
    uvh_plane_channels: int = 16
    """``uvh`` field: channels of each of the three learned planes (u, v), (u, h), (v, h)."""
    uvh_plane_resolution: int = 256
    """``uvh`` field: side of the (u, v) plane and width of the (u, h), (v, h) planes (texels across the
    atlas)."""
    uvh_plane_height: int = 64
    """``uvh`` field: texels of the (u, h) and (v, h) planes along h."""
    uvh_plane_lr_scale: float = 10.0
    """``uvh`` field: the tri-plane learns at ``lr`` times this (a texel is seen by few samples per step;
    grids train at 10 to 100 times an MLP's rate in instant-ngp)."""

    # ---- NeRF MLP M_NeRF (``model/nerf_mlp.py``; its depth and width also size the ``uvh`` field's head)
    mlp_depth: int = 6
    """Hidden Linear + ReLU layers (paper: 6)."""
    mlp_width: int = 256
    """Hidden width (paper: 256)."""
    density_activation: str = "softplus"
    """``"softplus"`` (default) or ``"trunc_exp"``. Never the raw output: the authors' code uses the unbounded
    head directly as alpha."""
    density_bias: float = -1.0
    """Added to the raw density before the activation (default -1.0, as in Mip-NeRF). With softplus the
    untrained density is then about 0.3 per metre: rays through a 1-2 m box start half transparent, so every
    sample gets gradient."""
    density_scale: float = 1.0
    """Multiplies the activated density (1/metre per unit; default 1)."""
    body_prior_strength: float = 0.0
    """Strength of a fixed raw-density offset from h (``nerf_mlp.body_density_prior``: +strength on and in
    the body, 0 at h = ``body_prior_width``, -strength from 2 ``body_prior_width`` out). 0 (default) is the
    paper's plain MLP."""
    body_prior_width: float = 0.15
    """Metres from the body surface at which the density prior of ``body_prior_strength`` crosses 0."""
    positional_encoding_freqs: int = 0
    """NeRF frequencies applied to b_o (paper: 0, none)."""
    atlas_feature_channels: int = 0
    """Channels of a learned feature texture on the body's UV atlas, read at each sample's atlas UV (the UV of
    b_o) and given to the MLP as one more input f^a (``model/nerf_mlp.py``). 0 (default): none, the paper's
    ``[b_o, h, f^d, f^s]``. The MLP alone learns fine appearance slowly from four smooth coordinates; a texture
    holds a free vector per texel (DNG's neural texture, here per 3D sample instead of per pixel)."""
    atlas_feature_levels: int = 4
    """Pyramid levels of the atlas feature texture, each half the previous side; their reads are summed."""
    atlas_feature_resolution: int = 256
    """Side of the atlas feature texture's finest level."""
    atlas_feature_lr_scale: float = 10.0
    """The atlas branch (texture and the MLP's weights on f^a) learns at ``lr`` times this: a texel is seen by
    few samples per step, and grids train at about 100x an MLP's rate in instant-ngp."""

    # ---- Sampling (``model/samplers.py``, ``model/volume_rendering.py``)
    samples_per_ray: int = 64
    """Stratified samples between box entry and exit (paper: 64; no importance pass). With
    ``importance_samples`` these are the coarse pass's."""
    importance_samples: int = 0
    """0 (the paper): the field is trained and rendered on the ``samples_per_ray`` stratified samples. > 0:
    those are a coarse pass, evaluated without gradient, and this many samples per ray drawn from its
    weights are what the field is trained and rendered on (:mod:`~garmentnerf.model.importance_sampler`;
    NeRF's hierarchical sampling with one network). Evenly spaced samples 4 cm apart make a thin garment a
    fog at least that thick; drawn from the weights they crowd where the cloth is. Needs ``sampler="box"``;
    every preset then samples in the box (the shell's culls leave gaps the fine pass cannot tile). Measured
    on one frame, 300 steps (proxy PI1 against PC2b, docs/quality.md, "Where the samples go"): the garment
    -0.3 dB, the body +1.2, and the field still learns the cloth as a fog 7 to 11 cm deep; off by default."""
    importance_uniform_mix: float = 0.1
    """With ``importance_samples``: the share of each ray's sampling distribution spread uniformly over the
    ray's segment rather than by the coarse weights (empty space keeps some samples, so a floater the coarse
    pass missed is still seen and removed)."""
    bbox_padding: float = 0.05
    """Metres added on every side of the posed body's bounding box (paper code: 0.05)."""
    sampler: str = "box"
    """Where each ray's samples go, in training and in every render of the model. ``"box"`` (the
    paper): ``samples_per_ray`` stratified samples in the padded box of the posed body. ``"shell"``:
    only where the garment can be: inside the body inflated by the garment's height band (measured on
    the scene's training garments, per skin vertex), at most ``-h_min`` behind the first skin
    crossing, and inside the band (:class:`~garmentnerf.model.shell_sampler.ShellSampler` with
    occlusion and :class:`~garmentnerf.model.height_band.HeightBandFilter`, the ``full`` preset's
    culls). The field then never sees the rest of the box, so its density there means nothing and
    every render of such a model uses the shell, the ``reference`` preset included."""
    shell_spacing: str = "box"
    """With ``sampler="shell"``: ``"box"`` keeps the box sampler's bins that overlap the shell (the
    paper's quadrature on fewer samples: on the bundled scene 39 % of the box's before the band filter,
    25 % after it, ``docs/bench.json``'s ``full`` row); ``"shell"`` spaces ``samples_per_ray``
    stratified samples over each ray's shell segment (there about 1.6 times finer steps, 24 samples
    where the box has 15, at the box's cost per ray)."""

    # ---- Palette decoder M_D (``model/palette.py``)
    palette_size: int = 2
    """P, palette colors (paper: 2, garment p_G and body/other p_B). A layered garment (the dress) takes one
    color per layer, inner first, then the body's (3 for the dress): the segmentation term holds each
    layer's weight to its label share, so the previewer can recolour the layers apart. Through the weight
    head alone (``segmentation_head_only``) the layers of one color did not come apart (the trunk carries
    nothing that tells them apart; docs/quality.md, "The layered dress")."""
    decoder_upsample_steps: int = 2
    """Nearest x2 upsamplings (paper: 2, 128 -> 512)."""
    decoder_width: int = 64
    """Width of the first decoder conv, halved after every upsampling down to decoder_min_width (authors'
    code: 128 -> 64 -> 32)."""
    decoder_min_width: int = 32
    """Floor of the decoder widths (authors' code: 32)."""
    decoder_extra_layers: int = 2
    """Full-resolution conv3x3 + LeakyReLU layers after the upsampling (authors' code: 2)."""
    decoder_low_layers: int = 0
    """Conv3x3 + LeakyReLU layers of width decoder_width at the feature image's resolution, before the first
    upsampling (not in the paper: 0). A layer there costs a sixteenth of one at full resolution and widens
    the decoder's view of the feature image (the paper's M_D sees about 4 x 4 feature pixels). Measured on one
    frame, 300 steps (proxy PC3b against PC2b, 3 layers; docs/quality.md, "The garment against a flat
    colour"): -1.1 dB on the garment, its folds gone flat (sharpness 0.04); 0 by default."""
    radiance_activation: str = "softplus"
    """``"softplus"`` (default: unbounded above, shifted so the untrained radiance is 1) or ``"sigmoid"``. The
    palette starts at mean colors, so pixels brighter than the mean need r > 1, which a sigmoid cannot give."""
    radiance_channels: int = 3
    """3 (paper: r in R^3) or 1 (grey shading, which cannot absorb hue and so makes recoloring follow the
    palette more faithfully)."""
    offset_scale: float = 0.5
    """Offsets are ``offset_scale * tanh(.)`` (small, and bounded so a color p + o stays near [0, 1])."""
    blend_weight_floor: float = 0.05
    """Added after the softplus of the blend weights before they are normalised (authors' code: 0.05), so no
    palette color's weight reaches exactly 0 and the normalisation never divides by 0."""
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """RGB in [0, 1] the output is composited over (default black, the background of the ground-truth renders
    in ``garmentnerf.data.render_gt``)."""
    garment_label: int = 2
    """Label-map value of garment pixels (0 is background; a layered garment's layer k is ``garment_label +
    k``), the segmentation term's targets."""
    body_label: int = 1
    """Label-map value of body pixels (0 is background), used to initialise the palette from mean colors."""

    # ---- Ablations
    use_dynamic_feature: bool = True
    """Feed f^s_t (from E) to the MLP (paper: on)."""
    use_detail_feature: bool = True
    """Feed f^d_t (from G_img + G_en) to the MLP (paper: on)."""
    detail_selection: str = "visibility"
    """How a sample's detail feature is taken from the front or back map: ``"visibility"`` (paper: the map
    whose reference camera sees the projected body point) or ``"soft_normal"`` (authors' code: weights
    (cos + 1) / 2 with cos between the body normal and the direction to each camera, the pair L2-normalised)."""

    # ---- Losses (paper Eq. for L; weights lambda_1..5)
    w_image: float = 1.0
    """L1 on the image (paper lambda_1 = 1)."""
    w_image_l2: float = 0.0
    """Mean squared error on the image, beside the L1 (not in the paper; 0: none). Where a model cannot
    predict a pixel the L1 learns the median of what it has seen there and PSNR scores the mean: every
    model's garment renders 8 to 22 % darker than the truth on average, on views it was trained on
    (docs/quality.md, "The lights"). Its gradient is 2 x the error, so about 10 balances the L1's at a
    typical 0.05 error."""
    w_mask: float = 1.0
    """L1 on the mask (paper: inside L_img, weight 1)."""
    w_perceptual: float = 0.1
    """VGG/perceptual term (paper lambda_2 = 0.1)."""
    perceptual_downsample: int = 1
    """The NeRF's perceptual term compares the image and its target area-averaged by this factor (1: at the
    training resolution, as the paper). G_img's pre-training keeps its term at full resolution. Must divide
    ``image_resolution``. At 2 the term costs 3.4 times less. Where it pays depends on the stage
    (docs/quality.md):
    - Where every weight trains, it did not pay at equal CPU time: a UV-h step was 1.18x cheaper, and recipe
      V1 lost 0.2 dB of foreground on the unseen views and 0.4 on the unseen motion to E1, and 1.2 to 1.4 dB
      of body. Hence the default of 1.
    - In a codes-only stage, where the field and the body are held, the step is 1.29x cheaper. Over 1,200
      steps it gained 0.11 dB of foreground at equal CPU (proxies PD1, PD2E). Over the bundle's 6,400 steps
      it cost 0.12 dB at equal steps (C7C10H), and 0.13 after 2,400 more (C7C11H). At equal CPU time
      (8,256 + 3,096 steps, C7C11HE) it gained 0.22 dB of foreground over the bundled C7C11, on 90 of 120
      views: the codes stage's term is worth taking at 2."""
    w_sparsity: float = 2e-4
    """Blend-weight sparsity (paper lambda_3 = 2e-4)."""
    w_offset: float = 0.03
    """Color-offset magnitude (paper lambda_4 = 0.03)."""
    w_palette: float = 1e-3
    """Palette drift from its initialisation (paper lambda_5 = 1e-3)."""
    w_opacity: float = 1.0
    """L1 between the volume-rendered opacity of the feature rays and the ground-truth mask area-averaged to
    the feature resolution (not in the paper: 0 gives the paper's objective). Default 1: the paper's only
    geometry signal reaches the density through the decoder's mask, which at a few thousand steps leaves the
    density at its uniform initial box (the decoder learns "features -> background" first); supervising the
    opacity directly carves the body and garment within a few hundred steps."""
    w_segmentation: float = 0.0
    """L1 between the garment blend weight w_G (palette color 0) and the ground-truth garment share of each
    foreground pixel, from the label maps (not in the paper: 0 gives its objective). The paper leaves the
    garment/body split to the sparsity and offset losses alone; at CPU schedules that split comes out wrong (a
    model at NeRF step 400 put w_G = 0.06 on garment pixels and made them blue with a body offset of 0.28),
    and recoloring the garment then barely changes it. The labels the palette is initialised from already say
    which pixels are garment."""
    w_plane_tv: float = 0.0
    """Total variation of the ``uvh`` field's learned tri-plane (K-Planes' regulariser; not in the paper, which
    has no planes; 0: off). Without it the shared planes, at ten times the rate, learn texel-scale noise that
    renders as fur on the skirt (E1 uvh: blurring its planes by 6 texels removes the fur and costs 0.4 dB on
    the garment, two held-out views of frame 20; docs/quality.md)."""
    w_occupancy: float = 0.0
    """Geometry supervision from the simulated garment (not in the paper; 0: off): the binary cross-entropy of
    the field's occupancy ``1 - exp(-sigma * occupancy_step)`` at ``occupancy_points`` points of the step's
    frame against *occupied* within ``occupancy_half_thickness`` of the garment's surface or inside the body
    (:mod:`garmentnerf.model.occupancy`). The images teach a frame's shape through one view per step; this
    term says where the whole frame's cloth is, every step, from the garment every scene sequence holds. At
    0.1 on E1's recipe from scratch (recipe O1, docs/quality.md) it gained 0.3 dB over the character and 0.4 on
    the garment on held-out cameras, IoU +0.01, and lost 0.2 dB on the held-out motion and 1.2 on the body:
    off until it wins on both."""
    w_distortion: float = 0.0
    """The distortion term of mip-NeRF 360 (not in the paper; 0: off): the mean over the feature rays of the
    expected distance between two points drawn from a ray's rendering weights
    (:func:`~garmentnerf.model.volume_rendering.distortion_packed`, metres). It is smallest when a ray's
    weight sits in one short interval, so it turns a fog into a surface and removes floaters; with
    ``importance_samples`` the intervals there are short enough for the surface to be a thin sheet. At 1.0
    (as large as the image term) on top of PI1 (proxy PI2) it narrowed the garment's fog by 14 to 19 % and
    left every figure within 0.05 dB of PI1's; off by default."""
    geometry_iterations: int = 0
    """NeRF steps at the start of the NeRF stage that train the occupancy term alone (a geometry warm-up, not
    in the paper; 0: none): nothing is rendered, a step costs E, G_en and the term's points, and every
    frame's whole garment is a target. They count in ``iterations`` and in the learning-rate schedule. A
    sequence model learns the average garment first; one frame's own shape (a hem swung out) shows only
    after many visits of each frame (docs/quality.md, "Telling the field where the cloth is"), which
    image steps are too dear to give. Recipe GW1 (2,000 of them, then 500 image steps, at E1's CPU time):
    the best silhouette on held-out cameras (IoU 0.946), 1.5 dB lost on the held-out motion and 4 on the
    body: the training frames' shapes do not carry to a new motion. Hence 0."""
    occupancy_points: int = 8192
    """Points per step of the occupancy term: half around the cloth, half uniform in the sampling box."""
    occupancy_half_thickness: float = 0.015
    """Half the thickness (metres) of the sheet around the garment's surface that counts as occupied: about
    half the sampler's interval (a 0.6 m deep box in 24 samples: 2.5 cm), so a ray's jittered samples meet
    the sheet as they would meet the density the images ask for."""
    occupancy_step: float = 0.025
    """Interval length (metres) that turns density into the occupancy of the term: about the sampler's."""
    occupancy_spread: float = 0.05
    """Standard deviation (metres) of the noise that moves garment vertices to the term's points around the
    cloth."""
    segmentation_start: int = 0
    """NeRF steps done before the segmentation term applies (a curriculum: the garment is first carved and
    colored by the image and mask losses, then assigned to its palette entry; the bundled model switched it
    on after 551 steps)."""
    segmentation_head_only: bool = True
    """The segmentation term trains only the decoder's weight head, not the layers it shares with the mask and
    radiance (nor the NeRF behind them). With the full gradient, switching the term on at NeRF step 551 of a
    run whose garment was already rendered collapsed the garment's mask from 0.96 to 0.03 within 65 steps;
    head-only, the mask stayed at 0.98 while w_G on the garment rose from 0.05 to 0.63 in 60 steps. From the
    first step (``segmentation_start`` 0) it is the other way round: head-only, the garment/body split of some
    runs from scratch never forms (the network paints the body with the garment's colour or the skirt with
    the skin's: G1, and the shell-sampled one-frame proxies), while with the full gradient it formed within 30
    steps in every run tried (``docs/quality.md``, "Sampling only where the garment can be")."""

    # ---- Optimisation
    lr: float = 5e-4
    """Initial Adam learning rate (paper: 5e-4)."""
    lr_final: float = 5e-5
    """Learning rate at the last iteration, exponential decay (paper: 5e-5)."""
    encoder_lr_scale: float = 1.0
    """In the NeRF stage the U-Nets E and G_en, which make the per-frame features f_d and f_s, learn at
    the scheduled rate times this (1: as every other network; the paper has no such scale). 10 lost
    0.83 dB on the garment of the demo's held-out cameras (recipe C15, ``docs/quality.md``)."""
    trained_parameters: tuple[str, ...] = ()
    """Prefixes of the parameter names (``model.named_parameters()``) the NeRF stage trains; every other
    weight is held exactly: left out of the optimiser, and no gradient is computed for it. Empty: every
    weight trains (the paper). ``("frame_codes.",)`` learns per-frame codes on a finished field. Before this
    setting such stages held the other weights with a tiny rate (``lr`` 1e-6 and a large
    ``frame_code_lr_scale``), and over 1,600 steps that drift cost 0.05 dB of garment on the motions
    without codes (``docs/quality.md``, "The bundled model C7C5"). A prefix no parameter has is an error."""
    iterations: int = 200_000
    """Training iterations (paper: 200k)."""
    batch_size: int = 1
    """Images per iteration and process (paper: 1): (frame, camera) pairs in the NeRF stage, frames
    in G_img pre-training. They are backpropagated one at a time and their gradients summed (each
    loss divided by the batch size), so memory stays that of one image and a step costs about
    ``batch_size`` single-image steps."""
    views_per_step: int = 1
    """Training cameras each image of a NeRF step renders of its frame (1: the paper's one). Above 1 the drawn
    (frame, camera) pair's camera and ``views_per_step - 1`` other training cameras, drawn from the step's
    generator, render the same frame: its encoders (E, G_en), planes and occupancy term are computed and
    backpropagated once for all of them, and the image terms are their mean (what a batch of those images
    would average). So a view costs less than an image of ``batch_size`` (the encoders are a fixed cost per
    frame: issue 27's "planes computed once per frame, reused across views"), at the price of fewer frames
    per view; the views' graphs are held together until the backward, so memory grows with them. Capped by
    the number of training cameras. On one frame at equal CPU time 2 views lost 0.25 dB of garment
    (``docs/quality.md``, proxy PV2)."""
    grad_clip_value: float = 40.0
    """Gradient clipping by value (authors' code: 40)."""
    generator_lr: float = 1e-4
    """Adam learning rate of G_img pre-training (DNG: 1e-4)."""
    generator_iterations: int = 100_000
    """G_img pre-training iterations (DNG: 100k)."""

    def __post_init__(self) -> None:
        self.background = tuple(float(c) for c in self.background)
        self.uvh_height_range = tuple(float(h) for h in self.uvh_height_range)
        self.velocity_smoothing = tuple(float(t) for t in self.velocity_smoothing)
        self.trained_parameters = tuple(str(p) for p in self.trained_parameters)
        self.validate()

    # ------------------------------------------------------------------ derived sizes
    @property
    def encoder_in_channels(self) -> int:
        """3 (k + 1 + m [+ 1]): normal map, k velocity maps, m smoothed velocity maps [, world normal map]."""
        return 3 * (self.history + 1 + len(self.velocity_smoothing) + int(self.world_normals))

    @property
    def zeta_channels(self) -> int:
        """Channels each sample carries into the volume rendering: zeta, then the shading normal when enabled."""
        return self.appearance_dim + 3 * int(self.shading_normals)

    @property
    def feature_image_channels(self) -> int:
        """Channels of F^zeta, the decoder's input: the rendered zeta_channels, then the depth normal when
        enabled."""
        return self.zeta_channels + 3 * int(self.depth_normals)

    @property
    def dynamic_encoder_channels(self) -> int:
        """Channels E emits: ``dynamic_feature_dim``, times ``uvh_slices`` for the ``uvh`` field, plus its
        ``uvh_sheet_layers``."""
        if self.field != "uvh":
            return self.dynamic_feature_dim
        return self.dynamic_feature_dim * self.uvh_slices + self.uvh_sheet_layers

    @property
    def geometry_dim(self) -> int:
        """Width of x^b = [b_o (positionally encoded), h]."""
        return 3 * (1 + 2 * self.positional_encoding_freqs) + 1

    @property
    def mlp_input_dim(self) -> int:
        """Width of the MLP input [b_o, h, f^d, f^s] (paper: 4 + 8 + 8 = 20); f^a enters beside it."""
        return (self.geometry_dim + self.detail_feature_dim * self.use_detail_feature
                + self.dynamic_feature_dim * self.use_dynamic_feature)

    @property
    def decoder_out_channels(self) -> int:
        """Raw channels of M_D: radiance, 3 offsets and 1 weight per color, mask (paper: 12 or 13)."""
        return self.radiance_channels + 4 * self.palette_size + 1

    def training_scale(self, width: int, height: int) -> float:
        """Pixels the model was trained at per pixel of a scene camera of ``width x height`` (the scene's
        image size): ``image_resolution / max(width, height)`` for whole-frame training, else
        ``training_crop_density``."""
        if self.training_crop_density > 0:
            return float(self.training_crop_density)
        return self.image_resolution / max(int(width), int(height))

    def training_camera(self, camera):
        """A scene camera (:class:`~garmentnerf.conventions.Camera`) at the density the model trains
        at: resized to ``image_resolution`` squared for whole-frame training (what the trainer has
        always rendered), else scaled by ``training_crop_density`` (each step renders a window of it)."""
        if self.training_crop_density <= 0:
            return camera.resized(self.image_resolution, self.image_resolution)
        s = float(self.training_crop_density)
        return camera.resized(max(1, round(camera.width * s)), max(1, round(camera.height * s)))

    # ------------------------------------------------------------------ checks
    def validate(self) -> None:
        """Raise ValueError on inconsistent or out-of-range settings."""
        def positive(*names):
            for name in names:
                if getattr(self, name) <= 0:
                    raise ValueError(f"ModelConfig.{name} must be positive, got {getattr(self, name)}")

        positive("info_map_resolution", "image_resolution", "reference_resolution", "feature_image_resolution",
                 "dynamic_feature_dim", "detail_feature_dim", "appearance_dim", "encoder_base_width", "encoder_depth",
                 "encoder_width_scale", "neural_texture_channels", "neural_texture_levels",
                 "neural_texture_resolution", "generator_width_scale", "mlp_depth", "mlp_width",
                 "samples_per_ray", "palette_size", "decoder_width", "decoder_min_width", "offset_scale",
                 "lr", "lr_final", "iterations", "batch_size", "views_per_step", "grad_clip_value", "generator_lr",
                 "generator_iterations", "atlas_feature_levels", "atlas_feature_resolution", "atlas_feature_lr_scale",
                 "encoder_lr_scale", "uvh_slices", "uvh_plane_channels", "uvh_plane_resolution", "uvh_plane_height",
                 "uvh_plane_lr_scale", "perceptual_downsample", "occupancy_points", "occupancy_half_thickness",
                 "occupancy_step", "occupancy_spread")
        if self.history < 0:
            raise ValueError(f"ModelConfig.history must be >= 0, got {self.history}")
        if any(not prefix for prefix in self.trained_parameters):
            raise ValueError(f"ModelConfig.trained_parameters: empty prefix in {list(self.trained_parameters)} "
                             "(leave the list empty to train every weight)")
        if not all(math.isfinite(t) and t > 0 for t in self.velocity_smoothing):
            raise ValueError(f"ModelConfig.velocity_smoothing must hold positive seconds, got "
                             f"{list(self.velocity_smoothing)}")
        if self.segmentation_start < 0:
            raise ValueError(f"ModelConfig.segmentation_start must be >= 0, got {self.segmentation_start}")
        if not (math.isfinite(self.shading_normal_blur) and self.shading_normal_blur >= 0):
            raise ValueError(f"ModelConfig.shading_normal_blur must be >= 0 metres, got {self.shading_normal_blur}")
        if self.shading_normal_blur > 0 and not self.shading_normals:
            raise ValueError("ModelConfig.shading_normal_blur needs shading_normals")
        if self.frame_code_resolution and not self.use_dynamic_feature:
            raise ValueError("ModelConfig.frame_code_resolution needs the dynamic feature (use_dynamic_feature)")
        if not (math.isfinite(self.frame_code_lr_scale) and self.frame_code_lr_scale > 0):
            raise ValueError(f"ModelConfig.frame_code_lr_scale must be > 0, got {self.frame_code_lr_scale}")
        if self.frame_code_support_margin < -1:
            raise ValueError(f"ModelConfig.frame_code_support_margin must be -1 (dense codes) or >= 0 texels, "
                             f"got {self.frame_code_support_margin}")
        if self.frame_code_support_margin >= 0 and not self.frame_code_resolution:
            raise ValueError("ModelConfig.frame_code_support_margin needs per-frame codes (frame_code_resolution)")
        if not (math.isfinite(self.frame_code_dropout) and 0 <= self.frame_code_dropout < 1):
            raise ValueError(f"ModelConfig.frame_code_dropout must lie in [0, 1), got {self.frame_code_dropout}")
        for name in ("positional_encoding_freqs", "atlas_feature_channels", "decoder_upsample_steps",
                     "decoder_extra_layers", "decoder_low_layers", "bbox_padding", "blend_weight_floor", "w_image",
                     "w_image_l2", "w_mask",
                     "w_perceptual", "w_sparsity", "w_offset", "w_palette", "w_opacity", "w_segmentation",
                     "w_plane_tv", "w_occupancy", "w_distortion", "frame_code_resolution", "frame_codes"):
            if getattr(self, name) < 0:
                raise ValueError(f"ModelConfig.{name} must be >= 0, got {getattr(self, name)}")
        if self.atlas_feature_resolution // 2 ** (self.atlas_feature_levels - 1) < 1:
            raise ValueError(f"ModelConfig.atlas_feature_levels ({self.atlas_feature_levels}) do not fit a "
                             f"{self.atlas_feature_resolution} texture")
        if self.field not in FIELDS:
            raise ValueError(f"ModelConfig.field must be one of {FIELDS}, got {self.field!r}")
        if self.sampler not in SAMPLERS:
            raise ValueError(f"ModelConfig.sampler must be one of {SAMPLERS}, got {self.sampler!r}")
        if self.importance_samples < 0:
            raise ValueError(f"ModelConfig.importance_samples must be >= 0, got {self.importance_samples}")
        if self.importance_samples and self.sampler != "box":
            raise ValueError("ModelConfig.importance_samples needs sampler 'box' (its coarse pass must tile each "
                             "ray's segment)")
        if not 0.0 <= self.importance_uniform_mix <= 1.0:
            raise ValueError(f"ModelConfig.importance_uniform_mix must be in [0, 1], got {self.importance_uniform_mix}")
        if self.shell_spacing not in SHELL_SPACINGS:
            raise ValueError(f"ModelConfig.shell_spacing must be one of {SHELL_SPACINGS}, got {self.shell_spacing!r}")
        for name in ("uvh_height_freqs", "uvh_canonical_freqs", "uvh_sheet_layers", "uvh_sheet_freqs"):
            if getattr(self, name) < 0:
                raise ValueError(f"ModelConfig.{name} must be >= 0, got {getattr(self, name)}")
        if self.uvh_canonical_freqs and self.field != "uvh":
            raise ValueError("ModelConfig.uvh_canonical_freqs belongs to the 'uvh' field")
        if self.uvh_sheet_layers and (self.field != "uvh" or not self.use_dynamic_feature):
            raise ValueError("ModelConfig.uvh_sheet_layers belongs to the 'uvh' field with its dynamic feature (E "
                             "emits the sheet heights)")
        if len(self.uvh_height_range) != 2 or not self.uvh_height_range[1] > self.uvh_height_range[0]:
            raise ValueError(f"ModelConfig.uvh_height_range must be (low, high) metres with high > low, "
                             f"got {self.uvh_height_range}")
        if self.field == "uvh" and (self.atlas_feature_channels or self.positional_encoding_freqs):
            raise ValueError("ModelConfig: atlas_feature_channels and positional_encoding_freqs belong to the "
                             "'paper' field; the 'uvh' field has its own tri-plane and height encoding")
        if self.density_activation not in DENSITY_ACTIVATIONS:
            raise ValueError(f"ModelConfig.density_activation must be one of {DENSITY_ACTIVATIONS}, "
                             f"got {self.density_activation!r}")
        if self.radiance_activation not in RADIANCE_ACTIVATIONS:
            raise ValueError(f"ModelConfig.radiance_activation must be one of {RADIANCE_ACTIVATIONS}, "
                             f"got {self.radiance_activation!r}")
        if self.detail_selection not in DETAIL_SELECTION_MODES:
            raise ValueError(f"ModelConfig.detail_selection must be one of {DETAIL_SELECTION_MODES}, "
                             f"got {self.detail_selection!r}")
        if self.radiance_channels not in (1, 3):
            raise ValueError(f"ModelConfig.radiance_channels must be 1 or 3, got {self.radiance_channels}")
        if len(self.background) != 3 or not all(0.0 <= c <= 1.0 for c in self.background):
            raise ValueError(f"ModelConfig.background must be 3 values in [0, 1], got {self.background}")
        if self.feature_image_resolution * 2 ** self.decoder_upsample_steps != self.image_resolution:
            raise ValueError(
                f"ModelConfig: feature_image_resolution ({self.feature_image_resolution}) x 2^decoder_upsample_steps "
                f"({2 ** self.decoder_upsample_steps}) must equal image_resolution ({self.image_resolution})")
        for name in ("info_map_resolution", "reference_resolution"):
            size = getattr(self, name)
            if size % 2 ** self.encoder_depth or size // 2 ** self.encoder_depth < 2:
                raise ValueError(f"ModelConfig.{name} ({size}) must be divisible by 2^encoder_depth "
                                 f"({2 ** self.encoder_depth}) with a bottleneck of at least 2x2")
        if not (self.training_crop_density >= 0 and self.training_crop_density < float("inf")):
            raise ValueError(f"ModelConfig.training_crop_density must be a number >= 0, "
                             f"got {self.training_crop_density}")
        if self.image_resolution % self.perceptual_downsample:
            raise ValueError(f"ModelConfig.perceptual_downsample ({self.perceptual_downsample}) must divide "
                             f"image_resolution ({self.image_resolution})")
        if not 0 <= self.geometry_iterations <= self.iterations:
            raise ValueError(f"ModelConfig.geometry_iterations ({self.geometry_iterations}) must lie in "
                             f"[0, iterations={self.iterations}]")
        if self.lr_final > self.lr:
            raise ValueError(f"ModelConfig.lr_final ({self.lr_final}) must not exceed lr ({self.lr})")
        if self.garment_label == self.body_label:
            raise ValueError("ModelConfig.garment_label and body_label must differ")

    # ------------------------------------------------------------------ presets
    @classmethod
    def paper(cls) -> "ModelConfig":
        """The published model (all defaults)."""
        return cls()

    @classmethod
    def cpu_small(cls) -> "ModelConfig":
        """A reduced model for a 2-core CPU (target: a usable model in about an hour).

        64 x 64 rays of 24 samples (at most 98k MLP points per image, fewer once rays missing
        the body box are skipped), a 4 x 128 MLP, 64-d zeta, U-Nets at half width, a 256 x 256
        output image and 128 x 128 reference images (G_en at 256 x 256 would cost more than all
        the rest). The info maps stay at 128 x 128.

        Measured on the 2 shared CPU cores of the development machine (min of 4, fwd + bwd): E
        0.08 s, G_en on both references 0.2 s, the MLP on 49k points (half the rays, about
        those that hit the body box) 0.4 s, M_D 0.12 s: about 1 s per iteration, hence 3000 iterations for an
        hour. G_img pre-training at 128 x 128 costs about 0.2 s per iteration.

        A few thousand steps is about 1% of the paper's schedule, so the density is made quick to
        move: ``trunc_exp`` with ``density_scale`` 10 and ``density_bias`` -3 (about 0.5 per
        metre untrained, as with the default softplus, but each unit of raw output multiplies the
        density by e), and a 2x larger learning rate (1e-3 decaying to 1e-4). The radiance is grey
        (``radiance_channels=1``): after 1,800 steps an RGB radiance had absorbed the garment's hue
        (garment pixels blended 71% of the *body* color, tinted blue by r), so recoloring the
        garment entry barely changed the garment. With a grey radiance the blend weights went wrong
        instead (see ``w_segmentation``), so they are supervised with the garment labels
        (``w_segmentation`` 0.5 after 550 NeRF steps).
        """
        return cls(
            image_resolution=256,
            reference_resolution=128,
            feature_image_resolution=64,
            appearance_dim=64,
            encoder_width_scale=0.5,
            neural_texture_resolution=256,
            generator_width_scale=0.5,
            mlp_depth=4,
            mlp_width=128,
            samples_per_ray=24,
            decoder_width=32,
            decoder_min_width=16,
            decoder_extra_layers=1,
            density_activation="trunc_exp",
            density_scale=10.0,
            density_bias=-3.0,
            body_prior_strength=3.0,
            body_prior_width=0.15,
            radiance_channels=1,
            w_segmentation=0.5,
            segmentation_start=550,
            lr=1e-3,
            lr_final=1e-4,
            iterations=3_000,
            generator_iterations=3_000,
        )

    # ------------------------------------------------------------------ checkpoints
    def to_dict(self) -> dict:
        """Plain JSON-compatible dict of every field."""
        out = dataclasses.asdict(self)
        out["background"] = list(self.background)
        out["uvh_height_range"] = list(self.uvh_height_range)
        out["velocity_smoothing"] = list(self.velocity_smoothing)
        out["trained_parameters"] = list(self.trained_parameters)
        return out

    @classmethod
    def from_dict(cls, data: dict) -> "ModelConfig":
        """Rebuild from :meth:`to_dict`; missing keys take the defaults, unknown keys raise."""
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"unknown ModelConfig key(s): {', '.join(unknown)} "
                             f"(known: {', '.join(sorted(known))})")
        return cls(**data)

    def replace(self, **changes) -> "ModelConfig":
        """A copy with some fields changed (validated)."""
        return dataclasses.replace(self, **changes)


__all__ = ["ModelConfig", "FIELDS", "SAMPLERS", "SHELL_SPACINGS", "DETAIL_SELECTION_MODES", "DENSITY_ACTIVATIONS", "RADIANCE_ACTIVATIONS"]
