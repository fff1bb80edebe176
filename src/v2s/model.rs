//! The V2S network: a 3-D U-Net (after Pfeiffer et al., MICCAI 2020, V2S-Net) from the input
//! channels on the grid (`[B, INPUTS, n, n, n]`) to a displacement field on the same grid
//! (`[B, 3, n, n, n]`, in [`super::OUTPUT_UNIT_MM`]).
//!
//! Level `l` (0 at full resolution) has `width·2^l` channels. Down: `convs` 3³ convolutions
//! (padding 1, ELU) per level, then a 2³ convolution of stride 2 to the next level. Up: a 2³
//! transposed convolution of stride 2 back to level `l`, concatenated with level `l`'s features
//! from the way down (the skip connection), then `convs` 3³ convolutions. A 1³ convolution maps
//! the level-0 features to the three displacement components; it starts at zero, so an
//! untrained network answers the rigid registration.

use burn::config::Config;
use burn::module::Module;
use burn::nn::conv::{Conv3d, Conv3dConfig, ConvTranspose3d, ConvTranspose3dConfig};
use burn::nn::{GroupNorm, GroupNormConfig, Initializer, PaddingConfig3d};
use burn::tensor::activation::elu;
use burn::tensor::{Device, Tensor};

use super::{INPUTS, V2sError};

/// Architecture of the V2S U-Net and its grid.
#[derive(Config, Debug, PartialEq)]
pub struct V2sConfig {
    /// Grid points per axis (the paper: 64; a multiple of `2^depth`). 16 by default, for CPU
    /// training: on two cores a training step costs 0.03 s at 16³ and 0.21 s at 32³ (7×; 64³
    /// another 8×), and within the same minutes the 16³ network trains 7× as many epochs, which
    /// mattered more (BENCHMARKS.md, "V2S").
    #[config(default = 16)]
    pub grid: usize,
    /// The grid cube's side beyond the preoperative liver's longest bounding-box edge, as a
    /// fraction of it on each side.
    #[config(default = 0.15)]
    pub margin: f64,
    /// Channels at full resolution (doubled at each level down).
    #[config(default = 8)]
    pub width: usize,
    /// Down-sampling steps (levels below full resolution; the coarsest level has
    /// `grid / 2^depth` points per axis).
    #[config(default = 2)]
    pub depth: usize,
    /// 3³ convolutions per level on each side of the U.
    #[config(default = 2)]
    pub convs: usize,
    /// Group normalisation after every convolution but the head (groups of about 4 channels;
    /// [`groups`]), as 3-D U-Nets for registration use: without it the un-normalised stack of
    /// 13 convolutions diverged under Adam at learning rates above 1e-3 (non-finite loss after
    /// 40–160 steps on the small preset), and trained slowly below.
    #[config(default = true)]
    pub norm: bool,
}

/// Groups of the group normalisation of `channels` channels: the most that divide them with at
/// least 4 channels each (one when there are fewer than 8).
pub fn groups(channels: usize) -> usize {
    (1..=(channels / 4).max(1))
        .rev()
        .find(|g| channels % g == 0)
        .unwrap_or(1)
}

/// A convolution, its normalisation (optional) and an ELU.
#[derive(Module, Debug)]
pub struct ConvBlock {
    /// The convolution.
    pub conv: Conv3d,
    /// Group normalisation of its output.
    pub norm: Option<GroupNorm>,
}

/// `ELU(norm(y))`, or `ELU(y)` without a normalisation.
fn norm_elu(norm: &Option<GroupNorm>, y: Tensor<5>) -> Tensor<5> {
    elu(
        match norm {
            Some(n) => n.forward(y),
            None => y,
        },
        1.0,
    )
}

impl ConvBlock {
    fn forward(&self, x: Tensor<5>) -> Tensor<5> {
        norm_elu(&self.norm, self.conv.forward(x))
    }
}

/// A transposed convolution (up-sampling), its normalisation (optional) and an ELU.
#[derive(Module, Debug)]
pub struct UpBlock {
    /// The transposed convolution.
    pub conv: ConvTranspose3d,
    /// Group normalisation of its output.
    pub norm: Option<GroupNorm>,
}

impl UpBlock {
    fn forward(&self, x: Tensor<5>) -> Tensor<5> {
        norm_elu(&self.norm, self.conv.forward(x))
    }
}

impl V2sConfig {
    /// Checks the settings.
    pub fn validate(&self) -> Result<(), V2sError> {
        if self.width == 0 || self.convs == 0 {
            return Err(V2sError::Invalid("width and convs must be positive".into()));
        }
        if self.depth > 5 {
            return Err(V2sError::Invalid(format!(
                "depth {} (at most 5)",
                self.depth
            )));
        }
        let step = 1usize << self.depth;
        if self.grid < 2 * step || self.grid % step != 0 || self.grid > 128 {
            return Err(V2sError::Invalid(format!(
                "grid {} must be a multiple of 2^depth = {step}, at least {}, at most 128",
                self.grid,
                2 * step
            )));
        }
        if !(self.margin.is_finite() && (0.0..=1.0).contains(&self.margin)) {
            return Err(V2sError::Invalid(format!(
                "margin {} (a fraction in [0, 1])",
                self.margin
            )));
        }
        Ok(())
    }

    /// Channels at level `l`.
    pub fn channels(&self, l: usize) -> usize {
        self.width << l
    }

    /// Initialises the network (weights from the device's random generator: seed it first).
    pub fn init(&self, device: &Device) -> Result<V2sNet, V2sError> {
        self.validate()?;
        let norm = |c: usize| {
            self.norm
                .then(|| GroupNormConfig::new(groups(c), c).init(device))
        };
        let conv3 = |cin: usize, cout: usize| ConvBlock {
            conv: Conv3dConfig::new([cin, cout], [3, 3, 3])
                .with_padding(PaddingConfig3d::Explicit(1, 1, 1))
                .init(device),
            norm: norm(cout),
        };
        let block = |cin: usize, cout: usize| -> Vec<ConvBlock> {
            (0..self.convs)
                .map(|k| conv3(if k == 0 { cin } else { cout }, cout))
                .collect()
        };
        let d = self.depth;
        let encoder = (0..=d)
            .map(|l| {
                let cin = if l == 0 { INPUTS } else { self.channels(l) };
                block(cin, self.channels(l))
            })
            .collect();
        let down = (0..d)
            .map(|l| ConvBlock {
                conv: Conv3dConfig::new([self.channels(l), self.channels(l + 1)], [2, 2, 2])
                    .with_stride([2, 2, 2])
                    .init(device),
                norm: norm(self.channels(l + 1)),
            })
            .collect();
        let up = (0..d)
            .map(|l| UpBlock {
                conv: ConvTranspose3dConfig::new(
                    [self.channels(l + 1), self.channels(l)],
                    [2, 2, 2],
                )
                .with_stride([2, 2, 2])
                .init(device),
                norm: norm(self.channels(l)),
            })
            .collect();
        let decoder = (0..d)
            .map(|l| block(2 * self.channels(l), self.channels(l)))
            .collect();
        let head = Conv3dConfig::new([self.channels(0), 3], [1, 1, 1])
            .with_initializer(Initializer::Zeros)
            .init(device);
        Ok(V2sNet {
            encoder,
            down,
            up,
            decoder,
            head,
        })
    }
}

/// The V2S U-Net.
#[derive(Module, Debug)]
pub struct V2sNet {
    /// Per level `0..=depth`: its 3³ convolutions on the way down (the last level is the
    /// bottleneck).
    pub encoder: Vec<Vec<ConvBlock>>,
    /// Per level `0..depth`: the stride-2 convolution to level `l + 1`.
    pub down: Vec<ConvBlock>,
    /// Per level `0..depth`: the stride-2 transposed convolution from level `l + 1`.
    pub up: Vec<UpBlock>,
    /// Per level `0..depth`: its 3³ convolutions on the way up (the first takes the skip and
    /// the up-sampled features, concatenated).
    pub decoder: Vec<Vec<ConvBlock>>,
    /// Level-0 features → displacement (1³ convolution).
    pub head: Conv3d,
}

impl V2sNet {
    /// The displacement field on the grid.
    ///
    /// # Shapes
    /// - `x`: `[B, INPUTS, n, n, n]` with `n` a multiple of `2^depth`
    /// - returns `[B, 3, n, n, n]` (output units)
    pub fn forward(&self, x: Tensor<5>) -> Result<Tensor<5>, V2sError> {
        let [_, c, n0, n1, n2] = x.dims();
        let depth = self.down.len();
        let step = 1usize << depth;
        if c != INPUTS || n0 != n1 || n1 != n2 || n0 % step != 0 || n0 < step {
            return Err(V2sError::Invalid(format!(
                "V2S input of shape {:?}: expected [B, {INPUTS}, n, n, n] with n a multiple of {step}",
                x.dims()
            )));
        }
        let run = |convs: &[ConvBlock], mut x: Tensor<5>| {
            for conv in convs {
                x = conv.forward(x);
            }
            x
        };
        let mut skips = Vec::with_capacity(depth);
        let mut x = x;
        for l in 0..depth {
            x = run(&self.encoder[l], x);
            skips.push(x.clone());
            x = self.down[l].forward(x);
        }
        x = run(&self.encoder[depth], x);
        for l in (0..depth).rev() {
            let up = self.up[l].forward(x);
            let skip = skips
                .pop()
                .ok_or_else(|| V2sError::Invalid("U-Net skip".into()))?;
            x = run(&self.decoder[l], Tensor::cat(vec![skip, up], 1));
        }
        Ok(self.head.forward(x))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::TensorData;

    fn values<const D: usize>(t: Tensor<D>) -> Vec<f32> {
        t.into_data().convert::<f32>().try_to_vec::<f32>().unwrap()
    }

    /// A 3-D convolution by its definition: `y[o, x] = b[o] + Σ_{c, k} w[o, c, k] · in[c, s·x + k − p]`
    /// (zero outside), on one batch.
    #[allow(clippy::too_many_arguments)]
    fn direct_conv3d(
        input: &[f32],
        cin: usize,
        n: usize,
        w: &[f32],
        b: &[f32],
        cout: usize,
        k: usize,
        stride: usize,
        pad: usize,
    ) -> (Vec<f32>, usize) {
        let m = (n + 2 * pad - k) / stride + 1;
        let mut out = vec![0.0f32; cout * m * m * m];
        for o in 0..cout {
            for x in 0..m {
                for y in 0..m {
                    for z in 0..m {
                        let mut s = b[o] as f64;
                        for c in 0..cin {
                            for a in 0..k {
                                for bb in 0..k {
                                    for cc in 0..k {
                                        let (i, j, l) = (
                                            (stride * x + a) as isize - pad as isize,
                                            (stride * y + bb) as isize - pad as isize,
                                            (stride * z + cc) as isize - pad as isize,
                                        );
                                        let n = n as isize;
                                        if i < 0 || j < 0 || l < 0 || i >= n || j >= n || l >= n {
                                            continue;
                                        }
                                        let (i, j, l) = (i as usize, j as usize, l as usize);
                                        let nn = n as usize;
                                        let v = input[((c * nn + i) * nn + j) * nn + l] as f64;
                                        let wv =
                                            w[(((o * cin + c) * k + a) * k + bb) * k + cc] as f64;
                                        s += wv * v;
                                    }
                                }
                            }
                        }
                        out[((o * m + x) * m + y) * m + z] = s as f32;
                    }
                }
            }
        }
        (out, m)
    }

    #[test]
    fn burn_conv3d_matches_a_direct_loop_with_padding_and_stride() {
        let device = Device::flex();
        device.seed(5);
        let (cin, cout, n) = (2, 3, 5);
        let input: Vec<f32> = (0..cin * n * n * n)
            .map(|i| ((i * 37 % 101) as f32 / 50.0) - 1.0)
            .collect();
        let x = Tensor::<5>::from_data(TensorData::new(input.clone(), [1, cin, n, n, n]), &device);
        for (k, stride, pad) in [(3, 1, 1), (2, 2, 0), (3, 2, 1)] {
            let conv = Conv3dConfig::new([cin, cout], [k, k, k])
                .with_stride([stride; 3])
                .with_padding(PaddingConfig3d::Explicit(pad, pad, pad))
                .init(&device);
            let w = values(conv.weight.val());
            let b = values(conv.bias.as_ref().unwrap().val());
            let got = conv.forward(x.clone());
            let (want, m) = direct_conv3d(&input, cin, n, &w, &b, cout, k, stride, pad);
            assert_eq!(got.dims(), [1, cout, m, m, m], "k {k} stride {stride}");
            let got = values(got);
            let worst = got
                .iter()
                .zip(&want)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0f32, f32::max);
            assert!(worst < 1e-5, "k {k} stride {stride} pad {pad}: {worst}");
        }
    }

    #[test]
    fn the_transposed_convolution_of_stride_two_spreads_each_voxel_onto_its_block() {
        let device = Device::flex();
        device.seed(9);
        let (cin, cout, n) = (2, 2, 3);
        let up = ConvTranspose3dConfig::new([cin, cout], [2, 2, 2])
            .with_stride([2, 2, 2])
            .init(&device);
        let input: Vec<f32> = (0..cin * n * n * n)
            .map(|i| (i as f32 * 0.13).sin())
            .collect();
        let x = Tensor::<5>::from_data(TensorData::new(input.clone(), [1, cin, n, n, n]), &device);
        // Weight [cin, cout, 2, 2, 2]: y[o, 2x + a] = b[o] + Σ_c w[c, o, a] · in[c, x].
        let w = values(up.weight.val());
        let b = values(up.bias.as_ref().unwrap().val());
        let got = up.forward(x);
        assert_eq!(got.dims(), [1, cout, 2 * n, 2 * n, 2 * n]);
        let got = values(got);
        let m = 2 * n;
        let mut worst = 0.0f32;
        for o in 0..cout {
            for i in 0..m {
                for j in 0..m {
                    for l in 0..m {
                        let mut s = b[o];
                        for c in 0..cin {
                            let v = input[((c * n + i / 2) * n + j / 2) * n + l / 2];
                            let wv = w[(((c * cout + o) * 2 + i % 2) * 2 + j % 2) * 2 + l % 2];
                            s += wv * v;
                        }
                        worst = worst.max((got[((o * m + i) * m + j) * m + l] - s).abs());
                    }
                }
            }
        }
        assert!(worst < 1e-5, "{worst}");
    }

    #[test]
    fn the_u_net_keeps_the_grid_shape_and_starts_at_zero() {
        let device = Device::flex();
        device.seed(1);
        let cfg = V2sConfig::new().with_grid(16).with_width(4).with_depth(2);
        let net = cfg.init(&device).unwrap();
        assert_eq!(net.encoder.len(), 3);
        assert_eq!(net.down.len(), 2);
        assert_eq!(net.up.len(), 2);
        assert_eq!(net.decoder.len(), 2);
        // Level 2 has 16 channels; the level-1 decoder takes 8 skip + 8 up-sampled.
        assert_eq!(net.encoder[2][0].conv.weight.dims(), [16, 16, 3, 3, 3]);
        assert_eq!(net.decoder[1][0].conv.weight.dims(), [8, 16, 3, 3, 3]);
        assert_eq!(net.up[1].conv.weight.dims(), [16, 8, 2, 2, 2]);
        assert_eq!(net.encoder[2][0].norm.as_ref().unwrap().num_groups, 4);
        assert_eq!(
            (groups(4), groups(8), groups(12), groups(18), groups(64)),
            (1, 2, 3, 3, 16)
        );
        let x = Tensor::<5>::random(
            [2, INPUTS, 16, 16, 16],
            burn::tensor::Distribution::Normal(0.0, 1.0),
            &device,
        );
        let y = net.forward(x).unwrap();
        assert_eq!(y.dims(), [2, 3, 16, 16, 16]);
        assert!(values(y).iter().all(|v| *v == 0.0));
        // Wrong channel count or a grid not divisible by 2^depth: an error, not a panic.
        for shape in [
            [1, 3, 16, 16, 16],
            [1, INPUTS, 10, 10, 10],
            [1, INPUTS, 16, 16, 8],
        ] {
            let x = Tensor::<5>::zeros(shape, &device);
            assert!(matches!(net.forward(x), Err(V2sError::Invalid(_))));
        }
        for bad in [
            V2sConfig::new().with_grid(18),
            V2sConfig::new().with_grid(4),
            V2sConfig::new().with_width(0),
            V2sConfig::new().with_margin(-1.0),
        ] {
            assert!(bad.validate().is_err(), "{bad:?}");
        }
    }
}
