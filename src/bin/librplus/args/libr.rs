//! The LIBR and pipeline options every command that registers shares (`--lambda`,
//! `--iterations`, the pose search, adaptive LIBR, the hold, abstention), shown under their own
//! heading in `--help`, and the pipeline parameters they make.

use clap::Args;

/// LIBR options shared by `register` and `evaluate`.
#[derive(Args, Clone)]
#[command(
    next_help_heading = "LIBR and pipeline options (the same for every command that registers)"
)]
pub(crate) struct LibrOpts {
    /// LIBR strain-energy regularization λ (dimensionless; default 1e-3).
    #[arg(long)]
    pub(crate) lambda: Option<f64>,
    /// Most LIBR iterations (default 20).
    #[arg(long)]
    pub(crate) iterations: Option<usize>,
    /// LIBR control points (default 25; changes the cached basis).
    #[arg(long)]
    pub(crate) control_points: Option<usize>,
    /// Width σ of each control point's load, as a multiple of the control-point spacing
    /// (default 1.25; changes the cached basis).
    #[arg(long)]
    pub(crate) load_width: Option<f64>,
    /// LIBR+ only: most LIBR iterations of the data-consistency refit after the SR-GCN
    /// correction (default 5; 0: none)
    #[arg(long)]
    pub(crate) refit_iterations: Option<usize>,
    /// The rigid stage (wICP) registers the anterior-surface points alone, as Clements et al.
    /// and the LIBR+ paper's wICP baseline do; ultrasound points are then used by LIBR only
    #[arg(long)]
    pub(crate) wicp_surface_only: bool,
    /// The navigation system's initial alignment is trusted to this uncertainty (mm, RMS
    /// displacement over the organ): the rigid motion of wICP, LIBR and the refit is
    /// regularised towards it instead of fitted freely (an organ held in place)
    #[arg(long, value_name = "MM")]
    pub(crate) trusted_alignment: Option<f64>,
    /// The organ is held in place and the navigation start trusted: the start is trusted to
    /// 5 mm (unless --trusted-alignment says otherwise), no pose search, and the surface no
    /// measured point comes near is held where the start puts it
    #[arg(long)]
    pub(crate) held: bool,
    /// LIBR+ never abstains: it corrects even registrations outside what its networks learned
    /// (their abstain.json; by default such a registration answers LIBR's result, flagged)
    #[arg(long)]
    pub(crate) no_abstain: bool,
    /// Auto without a trusted start: do not try the held variants (by default they are tried
    /// as a hypothesis, ranked after the free fits)
    #[arg(long)]
    pub(crate) auto_no_hold_hypothesis: bool,
    /// With --held: a boundary node is held when no measured point lies within this distance
    /// (mm, default 45)
    #[arg(long, value_name = "MM")]
    pub(crate) hold_clearance: Option<f64>,
    /// With --held: the held nodes' total weight relative to the data's (default 1)
    #[arg(long)]
    pub(crate) hold_weight: Option<f64>,
    /// With --held: at most this many held nodes, spread evenly over the held surface (default
    /// 128; 0: every node the clearance leaves)
    #[arg(long, value_name = "N")]
    pub(crate) hold_nodes: Option<usize>,
    /// Below this conditioning of the rigid stage's point-to-plane system the start is trusted
    /// to 10 mm and the registration flagged (default 1e-3; 0: never)
    #[arg(long)]
    pub(crate) min_conditioning: Option<f64>,
    /// Adaptive LIBR: control points of each level of its basis, broadest first, comma-separated
    /// (default 25,100; changes its cached basis)
    #[arg(long, value_delimiter = ',', value_name = "K,K,...")]
    pub(crate) adaptive_levels: Option<Vec<usize>>,
    /// Adaptive LIBR: a finer level's control load is kept when a matched point lies within this
    /// many patch widths of it (default 2)
    #[arg(long)]
    pub(crate) adaptive_reach: Option<f64>,
    /// Adaptive LIBR: the range of λ its evidence search covers (default 1e-3,1e-3: λ fixed at
    /// LIBR's; a wider range turns the search on)
    #[arg(long, value_delimiter = ',', value_name = "LOW,HIGH")]
    pub(crate) adaptive_lambda: Option<Vec<f64>>,
    /// Adaptive LIBR: stiffness annealing, the first iteration's least λ and the factor per
    /// iteration (default 0,0: none)
    #[arg(long, value_delimiter = ',', value_name = "START,FACTOR")]
    pub(crate) adaptive_anneal: Option<Vec<f64>>,
    /// Adaptive LIBR: the finer levels' deformation costs this many times its strain energy
    /// (default 1)
    #[arg(long)]
    pub(crate) adaptive_fine_penalty: Option<f64>,
    /// Adaptive LIBR: every level from the first iteration (default: the broadest level alone
    /// until it settles, then every level)
    #[arg(long)]
    pub(crate) adaptive_all_levels_at_once: bool,
    /// Adaptive LIBR: a finer control load is kept when the matched points near it spread at
    /// least this many patch widths across their second principal axis (default 0.3)
    #[arg(long)]
    pub(crate) adaptive_spread: Option<f64>,
    /// The rigid stage's extra starts: the navigation start turned by each of these angles
    /// (degrees) about three axes, both ways (default 15,30,45)
    #[arg(long, value_delimiter = ',', value_name = "DEG,...")]
    pub(crate) start_angles: Option<Vec<f64>>,
    /// The rigid stage starts from the navigation start alone (no pose search)
    #[arg(long, conflicts_with = "start_angles")]
    pub(crate) single_start: bool,
    /// The pose search runs only when the navigation start's own deformable fit scores above
    /// this (capped mean squared distance plus regularisation, mm²; default 4; 0: always)
    #[arg(long, value_name = "MM2")]
    pub(crate) search_above: Option<f64>,
    /// The deformable fit's regularisation term counts this many times in a pose's score
    /// (default 1)
    #[arg(long)]
    pub(crate) pose_energy_weight: Option<f64>,
    /// Weight of the misfit along a matched surface relative to across it (0: point-to-plane,
    /// the default; 1: point-to-point)
    #[arg(long)]
    pub(crate) tangential_weight: Option<f64>,
    /// Correspondences (the rigid stage's and LIBR's) weighted by a robust (Cauchy) kernel
    /// instead of trimmed by the median
    #[arg(long, conflicts_with = "trimmed_libr")]
    pub(crate) robust_kernel: bool,
    /// With --held: LIBR's correspondences trimmed by the median as usual instead of weighted
    /// by the robust kernel
    #[arg(long)]
    pub(crate) trimmed_libr: bool,
    /// Which model triangles surface points are matched to, kept at every stage: anterior or
    /// boundary (every boundary triangle: a patch seen from another side). Default: decided from
    /// the data (the anterior surface unless it leaves clearly more unexplained)
    #[arg(long, value_enum, value_name = "TARGET")]
    pub(crate) surface_target: Option<SurfaceTargetArg>,
    /// A surface cloud with more points than this many per triangle of the model's surface
    /// (and than 4,000) is reduced to about that many weighted cell centroids before every
    /// stage (default 0.5; 0: every point as sent)
    #[arg(long, value_name = "PER_TRIANGLE")]
    pub(crate) reduce_above: Option<f64>,
    /// The rigid stage's ICP iterations with Anderson acceleration (2–7 × fewer iterations;
    /// the answers move: docs/registration.md)
    #[arg(long)]
    pub(crate) accelerate: bool,
}

/// `--surface-target`'s values.
#[derive(Debug, Clone, Copy, clap::ValueEnum)]
pub(crate) enum SurfaceTargetArg {
    Anterior,
    Boundary,
}

impl LibrOpts {
    pub(crate) fn params(&self) -> librplus::pipeline::PipelineParams {
        let mut p = librplus::pipeline::PipelineParams::default();
        if let Some(l) = self.lambda {
            p.libr.fit.regularization = l;
        }
        if let Some(i) = self.iterations {
            p.libr.fit.max_iterations = i;
        }
        if let Some(k) = self.control_points {
            p.libr.basis.control_points = k;
        }
        if let Some(w) = self.load_width {
            p.libr.basis.load_width = librplus::register::libr::LoadWidth::Spacing(w);
        }
        if let Some(k) = self.refit_iterations {
            p.refit_iterations = k;
        }
        p.wicp.surface_only = self.wicp_surface_only;
        p.wicp.trusted_alignment_mm = self.trusted_alignment;
        p.held = self.held;
        p.auto.hypothesise_hold = !self.auto_no_hold_hypothesis;
        p.abstain = !self.no_abstain;
        if let Some(g) = self.search_above {
            p.pose.search_above_mm2 = g;
        }
        if let Some(w) = self.pose_energy_weight {
            p.pose.energy_weight = w;
        }
        p.wicp.correspondence.robust_kernel = self.robust_kernel;
        if let Some(t) = self.surface_target {
            use librplus::register::correspondence::SurfaceTarget;
            // A target named is a target kept: no side test.
            p.side.from_data = false;
            p.wicp.correspondence.surface_target = match t {
                SurfaceTargetArg::Anterior => SurfaceTarget::Anterior,
                SurfaceTargetArg::Boundary => SurfaceTarget::Boundary,
            };
        }
        p.hold.trimmed = self.trimmed_libr;
        if let Some(c) = self.reduce_above {
            p.reduce_above = c;
        }
        p.wicp.accelerate = self.accelerate;
        if let Some(w) = self.tangential_weight {
            p.libr.fit.tangential_weight = w;
        }
        if let Some(c) = self.hold_clearance {
            p.hold.clearance_mm = c;
        }
        if let Some(w) = self.hold_weight {
            p.hold.weight = w;
        }
        if let Some(n) = self.hold_nodes {
            p.hold.max_nodes = n;
        }
        if let Some(c) = self.min_conditioning {
            p.wicp.min_conditioning = c;
        }
        if let Some(levels) = &self.adaptive_levels {
            let w = p.libr.basis.load_width;
            p.adaptive.levels = levels.iter().map(|&k| (k, w)).collect();
        }
        if let Some(r) = self.adaptive_reach {
            p.adaptive.reach = r;
        }
        // Two values each; anything else becomes NaN, which the parameters' check refuses
        // naming the field.
        let pair = |v: &[f64]| match v {
            [a, b] => (*a, *b),
            _ => (f64::NAN, f64::NAN),
        };
        if let Some(l) = &self.adaptive_lambda {
            p.adaptive.lambda_range = pair(l);
        }
        if let Some(a) = &self.start_angles {
            p.pose.start_angles_deg = a.clone();
        }
        if self.single_start {
            p.pose.start_angles_deg.clear();
        }
        if let Some(x) = self.adaptive_spread {
            p.adaptive.spread = x;
        }
        if self.adaptive_all_levels_at_once {
            p.adaptive.coarse_first = false;
        }
        if let Some(f) = self.adaptive_fine_penalty {
            p.adaptive.fine_penalty = f;
        }
        if let Some(a) = &self.adaptive_anneal {
            (p.adaptive.anneal_start, p.adaptive.anneal_factor) = pair(a);
        }
        p
    }
}
