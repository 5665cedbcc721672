// The glossy kernels in lanes of `F` (`W` to a group), included by `reflectance.rs` in the
// modules `single` (`f32`, 16 lanes) and `double` (`f64`, 8 lanes), which define `F`, `W` and
// `table_lanes` (see `reflectance::single`). One text, two precisions.

/// One value per lane of a group.
pub(super) type Lanes = [F; W];

/// One `f64` per lane of a group (the point lights' geometry, the transmittance integral).
type Wide = [f64; W];

/// `W` lanes computed by `f`: straight-line code over the lanes, which the compiler turns into
/// vector instructions.
#[inline(always)]
fn lanes(f: impl FnMut(usize) -> F) -> Lanes {
    crate::lanes(f)
}

/// [`lanes`] of `f64`.
#[inline(always)]
fn wide(f: impl FnMut(usize) -> f64) -> Wide {
    crate::lanes(f)
}

/// `x` rounded to the lanes' type, coordinate by coordinate.
#[inline(always)]
fn to_lane(x: [f64; 3]) -> [F; 3] {
    x.map(|c| c as F)
}

/// `W` observations of a facet, one per lane (structure of arrays); a lane without an
/// observation has `l = 0` and never carries light.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct Group {
    pub(super) value: Lanes,
    pub(super) scale: Lanes,
    /// `l`, by coordinate.
    pub(super) l: [Lanes; 3],
    /// `h = normalize(l + v)`, by coordinate.
    pub(super) h: [Lanes; 3],
    /// `F(v.h) / F(1)`.
    pub(super) fresnel: Lanes,
    /// `(l.h)^2`, of which the retro-reflective diffuse term's `k` (see [`Diffuse::Retro`]);
    /// computed by [`Packed::prepare`] only for a lobe with that term.
    pub(super) retro: Lanes,
    /// Whether the lane's light is a point light whose direction and scale [`Packed::prepare`]
    /// computes (from `position`, `axis`, `mu` and the intensity `phi`).
    pub(super) point: [bool; W],
    pub(super) phi: Wide,
    pub(super) position: [Wide; 3],
    pub(super) axis: [Wide; 3],
    /// The LED anisotropy `mu` of a point light (0: isotropic).
    pub(super) mu: Wide,
}

/// The factors of a [`Group`] at a normal (see [`Shade`]): lanes that carry no light have
/// `lit` false (their other values are finite and unused).
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct Factors {
    pub(super) lit: [bool; W],
    pub(super) diffuse: Lanes,
    pub(super) specular: Lanes,
    pub(super) d_diffuse: [Lanes; 3],
    pub(super) d_specular: [Lanes; 3],
}

simd_dispatch! {
    wide
    /// [`prepare_groups`] with AVX-512 or AVX2 when the processor has it.
    fn prepare_dispatch => prepare_groups(
        groups: &mut [Group], v: [f64; 3], x: [f64; 3], eta: f64, retro: bool,
    ) -> ();
}

/// The point lights' directions and scales at `x` (in `f64`), the half vectors and the Fresnel
/// factors of `groups`, and with `retro` the `(l.h)^2` of the retro-reflective diffuse term (see
/// [`Packed::prepare`]).
// (Loops over the lanes by index: the form the compiler turns into vector instructions.)
#[allow(clippy::needless_range_loop)]
#[inline(always)]
fn prepare_groups(groups: &mut [Group], v: [f64; 3], x: [f64; 3], eta: f64, retro: bool) {
    let f1 = Lobe::new(0.0, eta).normal_reflectance();
    let inv_f1 = (1.0 / f1) as F;
    let (vf, etaf) = (to_lane(v), eta as F);
    for g in groups {
        if g.point.iter().any(|&p| p) {
            // beta = aniso (p - x) / |p - x|^3, aniso = max(0, -axis . (p - x) / |p - x|)^mu
            // for an LED: l = (p - x) / |p - x|, a = |beta| = aniso / |p - x|^2.
            let a: [Wide; 3] = coords!(|j| wide(|i| g.position[j][i] - x[j]));
            let id =
                wide(|i| 1.0 / (a[0][i] * a[0][i] + a[1][i] * a[1][i] + a[2][i] * a[2][i]).sqrt());
            let l: [Wide; 3] = coords!(|j| wide(|i| a[j][i] * id[i]));
            // aniso = t^mu, t = max(0, -axis . l): 1 for mu = 0, t for mu = 1 (as
            // `light::anisotropy`), else `power_lanes` once per other exponent of the group.
            let t = wide(|i| {
                (-(l[0][i] * g.axis[0][i] + l[1][i] * g.axis[1][i] + l[2][i] * g.axis[2][i]))
                    .max(0.0)
            });
            let mut aniso = wide(|i| if g.mu[i] == 0.0 { 1.0 } else { t[i] });
            if (0..W).any(|i| g.point[i] && g.mu[i] != 0.0 && g.mu[i] != 1.0) {
                other_exponents(&t, g, &mut aniso);
            }
            let lit: [bool; W] = crate::lanes(|i| aniso[i] > 0.0);
            let lf: [Lanes; 3] = coords!(|j| lanes(|i| l[j][i] as F));
            let scale = lanes(|i| (g.phi[i] * aniso[i] * id[i] * id[i]) as F);
            g.l = coords!(|j| {
                lanes(|i| match (g.point[i], lit[i]) {
                    (true, true) => lf[j][i],
                    (true, false) => 0.0,
                    (false, _) => g.l[j][i],
                })
            });
            g.scale = lanes(|i| if g.point[i] { scale[i] } else { g.scale[i] });
        }
        let a: [Lanes; 3] = coords!(|j| lanes(|i| g.l[j][i] + vf[j]));
        let inv =
            lanes(|i| 1.0 / (a[0][i] * a[0][i] + a[1][i] * a[1][i] + a[2][i] * a[2][i]).sqrt());
        g.h = coords!(|j| lanes(|i| a[j][i] * inv[i]));
        g.fresnel = if f1 > 1e-12 {
            let c = lanes(|i| vf[0] * g.h[0][i] + vf[1] * g.h[1][i] + vf[2] * g.h[2][i]);
            let d = fresnel_denominators(etaf, &c);
            let q = lanes(|i| 1.0 / (d.1[i] * d.2[i] * d.0[i]));
            let f = fresnel_lanes(etaf, &c, d, &q);
            lanes(|i| f[i] * inv_f1)
        } else {
            [1.0; W]
        };
        if retro {
            let cd =
                lanes(|i| g.l[0][i] * g.h[0][i] + g.l[1][i] * g.h[1][i] + g.l[2][i] * g.h[2][i]);
            g.retro = lanes(|i| cd[i] * cd[i]);
        }
    }
}

/// `t^mu` into `aniso` for the point lights of `g` whose `mu` is neither 0 nor 1, by
/// [`power_lanes`] once per such exponent. Out of line: inlined, it made [`prepare_groups`]
/// about 1.7 times as slow on rigs that never need it (perf samples of a 256² run, helper
/// i20-f32, stop 46).
#[inline(never)]
#[allow(clippy::needless_range_loop)]
fn other_exponents(t: &Wide, g: &Group, aniso: &mut Wide) {
    let mut done: [bool; W] = crate::lanes(|i| !g.point[i] || g.mu[i] == 0.0 || g.mu[i] == 1.0);
    while let Some(first) = done.iter().position(|&d| !d) {
        let mu = g.mu[first];
        let p = power_lanes(t, mu);
        for i in 0..W {
            if !done[i] && g.mu[i] == mu {
                aniso[i] = p[i];
                done[i] = true;
            }
        }
    }
}

/// The refracted cosines `t` and the denominators `c + eta t`, `eta c + t` of [`Lobe::fresnel`]
/// in lanes, for `eta > 1` and `0 <= c <= 1` (`t` is then positive).
#[inline(always)]
fn fresnel_denominators(eta: F, c: &Lanes) -> (Lanes, Lanes, Lanes) {
    let ie2 = 1.0 / (eta * eta);
    let t = lanes(|i| {
        (1.0 - (1.0 - c[i] * c[i]) * ie2)
            .max(F::MIN_POSITIVE)
            .sqrt()
    });
    let ds = lanes(|i| c[i] + eta * t[i]);
    let dp = lanes(|i| eta * c[i] + t[i]);
    (t, ds, dp)
}

/// The reflectance of [`Lobe::fresnel`] in lanes from [`fresnel_denominators`] and
/// `q = 1 / (ds dp t)`.
#[inline(always)]
fn fresnel_lanes(eta: F, c: &Lanes, (t, ds, dp): (Lanes, Lanes, Lanes), q: &Lanes) -> Lanes {
    let ids = lanes(|i| dp[i] * t[i] * q[i]);
    let idp = lanes(|i| ds[i] * t[i] * q[i]);
    let rs = lanes(|i| (c[i] - eta * t[i]) * ids[i]);
    let rp = lanes(|i| (eta * c[i] - t[i]) * idp[i]);
    lanes(|i| 0.5 * (rs[i] * rs[i] + rp[i] * rp[i]))
}

/// The terms of [`View`] that the lanes use, rounded to [`F`].
#[derive(Debug, Clone, Copy)]
struct LaneView {
    tv: F,
    dtv: F,
    gv: F,
    dgv: F,
}

impl LaneView {
    #[inline(always)]
    fn new(w: &View) -> LaneView {
        LaneView {
            tv: w.tv as F,
            dtv: w.dtv as F,
            gv: w.gv as F,
            dgv: w.dgv as F,
        }
    }
}

/// [`Kernel::shade`] (of `kernel`) of the observations of group `g` at the normal `n` with its
/// shared terms `w` (`v` the view vector), in lanes: the factors, their gradients only `GRADS`.
/// Lit lanes of a cosine `n.l` below [`LEAST_COSINE`] are evaluated at it.
#[inline(always)]
fn shade_group<const GRADS: bool>(
    kernel: &Kernel,
    g: &Group,
    n: [F; 3],
    w: &LaneView,
    v: [F; 3],
) -> Factors {
    let cl = lanes(|i| n[0] * g.l[0][i] + n[1] * g.l[1][i] + n[2] * g.l[2][i]);
    let lit: [bool; W] = crate::lanes(|i| cl[i] > 0.0);
    // Unlit lanes are evaluated at a harmless cosine and masked; the least cosine keeps the
    // product of the denominators below from underflowing (its factors are at least
    // `c alpha^2`, `alpha^2` and about `eta - 1`).
    let c = lanes(|i| if lit[i] { cl[i].max(LEAST_COSINE) } else { 1.0 });
    let ch = lanes(|i| n[0] * g.h[0][i] + n[1] * g.h[1][i] + n[2] * g.h[2][i]);
    let a2 = kernel.a2 as F;
    // The denominators of the GGX distribution and Smith's masking, inverted by one division.
    // The GGX one is `(n.h)^2 (alpha^2 - 1) + 1`; with `GGX_SUM` (the `f32` lanes) it is
    // computed as `alpha^2 (n.h)^2 + |n x h|^2`, a sum of two positive terms (`1 - (n.h)^2`
    // would cancel near the peak, where it is about `alpha^2`: in `f32` an error of
    // `1e-7 / alpha^2` relative, 4e-5 at `alpha = 0.05`; in `f64` `1e-16 / alpha^2`).
    let qg = if GGX_SUM {
        let s2 = lanes(|i| {
            let x = n[1] * g.h[2][i] - n[2] * g.h[1][i];
            let y = n[2] * g.h[0][i] - n[0] * g.h[2][i];
            let z = n[0] * g.h[1][i] - n[1] * g.h[0][i];
            x * x + y * y + z * z
        });
        lanes(|i| a2 * (ch[i] * ch[i]) + s2[i])
    } else {
        lanes(|i| ch[i] * ch[i] * (a2 - 1.0) + 1.0)
    };
    let r = lanes(|i| (a2 + (1.0 - a2) * c[i] * c[i]).sqrt());
    let qs = lanes(|i| c[i] * r[i] * (c[i] + r[i]));
    let ip = lanes(|i| 1.0 / (qg[i] * qs[i]));
    let iq = lanes(|i| ip[i] * qs[i]);
    let sw = lanes(|i| ip[i] * qg[i]);
    // The diffuse term's factor of the light `tl` (and its derivative), and of the view `tv`
    // (per light with the retro-reflective term).
    let retro = kernel.retro > 0.0;
    let (tl, dtl, tv, k) = if retro {
        // A = 1 + k F5(c), B = 1 + k F5(n.v), k = 2 R (l.h)^2 - 1/2 (see [`Kernel::shade`]).
        let weight = kernel.retro as F;
        let k = lanes(|i| weight * g.retro[i] - 0.5);
        let u = lanes(|i| 1.0 - c[i]);
        let u4 = lanes(|i| (u[i] * u[i]) * (u[i] * u[i]));
        (
            lanes(|i| 1.0 + k[i] * (u4[i] * u[i])),
            lanes(|i| -5.0 * k[i] * u4[i]),
            lanes(|i| 1.0 + k[i] * w.tv),
            k,
        )
    } else {
        let (tl, dtl) = match &kernel.table {
            None => ([1.0; W], [0.0; W]),
            Some(t) => table_lanes(t, &c),
        };
        (tl, dtl, [w.tv; W], [0.0; W])
    };
    let diffuse = lanes(|i| c[i] * tl[i] * tv[i]);
    let da = a2 * std::f64::consts::FRAC_1_PI as F;
    let specular = lanes(|i| {
        let d = da * iq[i] * iq[i];
        let gl = 2.0 * c[i] * c[i] * r[i] * sw[i];
        let s = g.fresnel[i] * d * gl * w.gv;
        if ch[i] > 0.0 {
            s
        } else {
            0.0
        }
    });
    let mut out = Factors {
        lit,
        diffuse,
        specular,
        ..Factors::default()
    };
    if GRADS {
        let wl = lanes(|i| (tl[i] + c[i] * dtl[i]) * tv[i]);
        let wv = match retro {
            true => lanes(|i| c[i] * tl[i] * k[i] * w.dtv),
            false => lanes(|i| c[i] * tl[i] * w.dtv),
        };
        let sh = lanes(|i| specular[i] * (-4.0 * ch[i] * (a2 - 1.0) * iq[i]));
        let sl = lanes(|i| specular[i] * (a2 * sw[i]));
        let sv = lanes(|i| specular[i] * w.dgv);
        out.d_diffuse = coords!(|j| lanes(|i| wl[i] * g.l[j][i] + wv[i] * v[j]));
        out.d_specular =
            coords!(|j| lanes(|i| sh[i] * g.h[j][i] + sl[i] * g.l[j][i] + sv[i] * v[j]));
    }
    out
}

/// The sums of the normal equations in lanes (see [`Accumulator::add`]).
struct Accumulator {
    /// The upper triangle of `J^T J`, row by row.
    jtj: [Lanes; 10],
    jtr: [Lanes; 4],
    sse: Lanes,
    used: [u32; W],
}

/// The squared residual, `J^T J`, `J^T r` and the number of observations used at `(b, s)`.
type Equations = (f64, Matrix4<f64>, Vector4<f64>, u32);

/// The sum of the lanes `x`, in `f64`.
#[inline(always)]
fn lane_sum(x: &Lanes) -> f64 {
    x.iter().map(|&v| f64::from(v)).sum()
}

impl Accumulator {
    #[inline(always)]
    fn new() -> Accumulator {
        Accumulator {
            jtj: [[0.0; W]; 10],
            jtr: [[0.0; W]; 4],
            sse: [0.0; W],
            used: [0; W],
        }
    }

    /// Adds group `g` with its factors `f` at `n`, `rho`, `s`.
    // (Loops over the lanes by index: the form the compiler turns into vector instructions.)
    #[allow(clippy::needless_range_loop)]
    #[inline(always)]
    fn add(&mut self, g: &Group, f: &Factors, n: [F; 3], rho: F, s: F) {
        let m = lanes(|i| if f.lit[i] { 1.0 } else { 0.0 });
        let r =
            lanes(|i| m[i] * (g.value[i] - g.scale[i] * (rho * f.diffuse[i] + s * f.specular[i])));
        // d m / d b = scale (D n + P grad D + (s / rho) P grad S), P = I - n n^T.
        let t = s / rho;
        let gr: [Lanes; 3] = coords!(|j| lanes(|i| f.d_diffuse[j][i] + t * f.d_specular[j][i]));
        let gn = lanes(|i| gr[0][i] * n[0] + gr[1][i] * n[1] + gr[2][i] * n[2]);
        let ms = lanes(|i| m[i] * g.scale[i]);
        let j: [Lanes; 4] = [
            lanes(|i| ms[i] * (f.diffuse[i] * n[0] + gr[0][i] - gn[i] * n[0])),
            lanes(|i| ms[i] * (f.diffuse[i] * n[1] + gr[1][i] - gn[i] * n[1])),
            lanes(|i| ms[i] * (f.diffuse[i] * n[2] + gr[2][i] - gn[i] * n[2])),
            lanes(|i| ms[i] * f.specular[i]),
        ];
        let mut e = 0;
        for a in 0..4 {
            for b in a..4 {
                for i in 0..W {
                    self.jtj[e][i] += j[a][i] * j[b][i];
                }
                e += 1;
            }
            for i in 0..W {
                self.jtr[a][i] += j[a][i] * r[i];
            }
        }
        for i in 0..W {
            self.sse[i] += r[i] * r[i];
            self.used[i] += u32::from(f.lit[i]);
        }
    }

    /// The lanes summed (in `f64`), one lane after another: out of line with
    /// `FINISH_OUT_OF_LINE` (the `f64` lanes), else inlined into the kernel.
    #[inline(always)]
    fn finish(self) -> Equations {
        match FINISH_OUT_OF_LINE {
            true => self.finish_apart(),
            false => self.sums(),
        }
    }

    /// [`Accumulator::finish`] out of line (as scalar code: no dispatch).
    #[inline(never)]
    fn finish_apart(self) -> Equations {
        self.sums()
    }

    /// The sums of [`Accumulator::finish`].
    #[inline(always)]
    fn sums(self) -> Equations {
        let mut m = Matrix4::zeros();
        let mut e = 0;
        for a in 0..4 {
            for b in a..4 {
                m[(a, b)] = lane_sum(&self.jtj[e]);
                m[(b, a)] = m[(a, b)];
                e += 1;
            }
        }
        (
            lane_sum(&self.sse),
            m,
            Vector4::from(self.jtr.map(|x| lane_sum(&x))),
            self.used.iter().sum(),
        )
    }
}

/// The factors of `groups` at the normal `n` (with its shared terms `w`) into `out`.
#[inline(always)]
pub(super) fn factors_of(
    k: &Kernel,
    groups: &[Group],
    n: [f64; 3],
    w: &View,
    v: [f64; 3],
    out: &mut [Factors],
) {
    let (n, w, v) = (to_lane(n), LaneView::new(w), to_lane(v));
    for (g, f) in groups.iter().zip(out) {
        *f = shade_group::<true>(k, g, n, &w, v);
    }
}

/// The normal equations at `(rho n, s)` from the factors at `n`.
#[inline(always)]
fn accumulate(groups: &[Group], factors: &[Factors], n: [f64; 3], rho: f64, s: f64) -> Equations {
    let mut acc = Accumulator::new();
    let n = to_lane(n);
    for (g, f) in groups.iter().zip(factors) {
        acc.add(g, f, n, rho as F, s as F);
    }
    acc.finish()
}

/// The model and its derivatives at `(b, s)`: the squared residual, `J^T J`, `J^T r` and the
/// number of observations used.
#[inline(always)]
fn equations_at(k: &Kernel, groups: &[Group], v: [f64; 3], b: [f64; 3], s: f64) -> Equations {
    let rho = norm(b);
    let n = scale(b, 1.0 / rho);
    let mut acc = Accumulator::new();
    if let Some(w) = k.view(n, v) {
        let (n, w, v) = (to_lane(n), LaneView::new(&w), to_lane(v));
        for g in groups {
            let f = shade_group::<true>(k, g, n, &w, v);
            acc.add(g, &f, n, rho as F, s as F);
        }
    }
    acc.finish()
}

/// The squared residual at `(b, s)` and the number of observations used (no derivatives).
#[inline(always)]
fn residual_at(k: &Kernel, groups: &[Group], v: [f64; 3], b: [f64; 3], s: f64) -> (f64, u32) {
    let rho = norm(b);
    let n = scale(b, 1.0 / rho);
    let (mut sse, mut used): (Lanes, [u32; W]) = ([0.0; W], [0u32; W]);
    if let Some(w) = k.view(n, v) {
        let (n, w, v) = (to_lane(n), LaneView::new(&w), to_lane(v));
        let (rho, s) = (rho as F, s as F);
        for g in groups {
            let f = shade_group::<false>(k, g, n, &w, v);
            for i in 0..W {
                let r = g.value[i] - g.scale[i] * (rho * f.diffuse[i] + s * f.specular[i]);
                sse[i] += if f.lit[i] { r * r } else { 0.0 };
                used[i] += u32::from(f.lit[i]);
            }
        }
    }
    (lane_sum(&sse), used.iter().sum())
}

/// The sums `d.d`, `d.s`, `s.s`, `d.i`, `s.i` over the lit observations of `groups` with their
/// `factors` (`d = Phi a D`, `s = Phi a S`, `i` the image values), in `f64` lanes (see
/// [`albedo_sums_in_order`] for the other order).
#[inline(always)]
fn albedo_sums(groups: &[Group], factors: &[Factors]) -> [f64; 5] {
    let mut acc = [[0.0; W]; 5];
    for (g, f) in groups.iter().zip(factors) {
        let m = wide(|i| if f.lit[i] { f64::from(g.scale[i]) } else { 0.0 });
        let d = wide(|i| m[i] * f64::from(f.diffuse[i]));
        let s = wide(|i| m[i] * f64::from(f.specular[i]));
        let value = wide(|i| f64::from(g.value[i]));
        let terms = [
            wide(|i| d[i] * d[i]),
            wide(|i| d[i] * s[i]),
            wide(|i| s[i] * s[i]),
            wide(|i| d[i] * value[i]),
            wide(|i| s[i] * value[i]),
        ];
        acc = crate::lanes(|k| wide(|i| acc[k][i] + terms[k][i]));
    }
    acc.map(|x| x.iter().sum())
}

/// The sums of [`albedo_sums`] in `f64`, one observation after another (group by group, lane by
/// lane): the order of the scalar loop of the `f64` kernels before the `f32` lanes (their bits),
/// without a dispatched call.
#[inline(always)]
fn albedo_sums_in_order(groups: &[Group], factors: &[Factors]) -> [f64; 5] {
    let [mut dd, mut ds, mut ss, mut di, mut si] = [0.0; 5];
    for (g, f) in groups.iter().zip(factors) {
        for i in 0..W {
            if f.lit[i] {
                let scale = f64::from(g.scale[i]);
                let (d, s) = (scale * f64::from(f.diffuse[i]), scale * f64::from(f.specular[i]));
                let value = f64::from(g.value[i]);
                dd += d * d;
                ds += d * s;
                ss += s * s;
                di += d * value;
                si += s * value;
            }
        }
    }
    [dd, ds, ss, di, si]
}

/// The least-squares albedos `(rho_d n, rho_s)` at the normal `n` held (`rho_s >= 0`; `rho_d`
/// from the diffuse part alone where the specular one would be negative), or None without
/// light; `factors` are those of `groups` at `n`. (In `f64`.)
#[inline(always)]
fn albedos_at(groups: &[Group], factors: &[Factors], n: [f64; 3]) -> Option<([f64; 3], f64)> {
    let [dd, ds, ss, di, si] = match LANE_ALBEDO_SUMS {
        true => albedo_sums(groups, factors),
        false => albedo_sums_in_order(groups, factors),
    };
    if dd <= 0.0 {
        return None;
    }
    let det = dd * ss - ds * ds;
    let (rho, s) = if det > 1e-12 * dd * ss && (dd * si - ds * di) > 0.0 {
        ((ss * di - ds * si) / det, (dd * si - ds * di) / det)
    } else {
        (di / dd, 0.0)
    };
    (rho > 0.0).then(|| (scale(n, rho), s))
}

/// `x^T a x`, written out (`nalgebra`'s product was a call out of line).
#[inline(always)]
fn quadratic(a: &Matrix4<f64>, x: &Vector4<f64>) -> f64 {
    let mut q = 0.0;
    for i in 0..4 {
        let row = a[(i, 0)] * x[0] + a[(i, 1)] * x[1] + a[(i, 2)] * x[2] + a[(i, 3)] * x[3];
        q += x[i] * row;
    }
    q
}

/// [`fit_from`] with the kernel `k` of its lobe, on the observations `obs` seen along `v`
/// with the noise variance `noise` (see [`Packed::noise`]).
#[allow(clippy::too_many_arguments)]
pub(super) fn fit_with(
    k: &Kernel,
    obs: &mut Store,
    v: [f64; 3],
    noise: f64,
    n0: [f64; 3],
    fallback: Option<[f64; 3]>,
    steps: usize,
    tolerance: f64,
) -> Option<GlossyFit> {
    fit_dispatch(k, obs, v, noise, n0, fallback, (steps, tolerance))
}

simd_dispatch! {
    wide
    /// [`fit_in_lanes`] with AVX-512 or AVX2 when the processor has it.
    fn fit_dispatch => fit_in_lanes(
        k: &Kernel,
        obs: &mut Store,
        v: [f64; 3],
        noise: f64,
        n0: [f64; 3],
        fallback: Option<[f64; 3]>,
        limits: (usize, f64),
    ) -> Option<GlossyFit>;
}

/// [`fit_with`] with its limits `(steps, tolerance)`: the whole fit one dispatched function,
/// its kernels (the factors, the albedos' sums, the normal equations, the residual) and the
/// view's terms inlined into it. (Each kernel was dispatched on its own, with `Kernel::view`
/// and the steps' scalar code between them compiled for the baseline processor.)
#[inline(always)]
fn fit_in_lanes(
    k: &Kernel,
    obs: &mut Store,
    v: [f64; 3],
    noise: f64,
    n0: [f64; 3],
    fallback: Option<[f64; 3]>,
    (steps, tolerance): (usize, f64),
) -> Option<GlossyFit> {
    // The factors at the starting normal serve both its albedos and its normal equations
    // (every entry is written: no clearing first).
    let n = obs.len.div_ceil(W);
    obs.factors.resize(n, Factors::default());
    match k.view(n0, v) {
        Some(w) => factors_of(k, &obs.all[..n], n0, &w, v, &mut obs.factors),
        None => obs.factors.fill(Factors::default()),
    }
    let groups = &obs.all[..n];
    let (mut b, mut s) = match albedos_at(groups, &obs.factors, n0) {
        Some(albedos) => albedos,
        None => (fallback?, 0.0),
    };
    let (mut sse, mut jtj, mut jtr, mut used) =
        accumulate(groups, &obs.factors, n0, norm(b), s);
    let mut lambda = 1e-3;
    // Whether the last allowed step was taken (the fit may not have reached its minimum).
    let mut capped = false;
    // The decrease the step at which the fit stopped promised (unknown: infinite).
    let mut promise = f64::INFINITY;
    // The length of the last step taken where the decrease it brought was the one the
    // linearised model predicted, within `SETTLED_MATCH` (see `SETTLED_RATIO`).
    let mut settled: Option<f64> = None;
    for step_index in 0..steps {
        if used < 4 {
            return None;
        }
        let last = step_index + 1 == steps;
        let mut accepted = false;
        for _ in 0..8 {
            let mut a = jtj;
            for i in 0..4 {
                a[(i, i)] += lambda * jtj[(i, i)].max(1e-300);
            }
            let Some(step) = solve_spd4(&a, &jtr) else {
                lambda *= 10.0;
                continue;
            };
            // The decrease the linearised model promises: none worth a trial at a minimum; nor
            // a step within the tolerance. (The tolerance moved the glossy distance search when
            // its candidates used it: the matte torus -0.00 % -> -1.10 %, the rough-plastic 0.3
            // block -0.86 % -> -2.91 % on the PBR renders; they fit with none.)
            if step.dot(&jtr) <= 1e-12 * sse
                || step.norm() <= tolerance * (norm(b) + s)
                || (tolerance > 0.0 && step.dot(&jtr) <= NOISE_STOP * noise)
            {
                promise = step.dot(&jtr);
                break;
            }
            let nb = [b[0] + step[0], b[1] + step[1], b[2] + step[2]];
            let ns = (s + step[3]).max(0.0);
            if norm(nb) == 0.0 || !nb.iter().all(|x| x.is_finite()) {
                lambda *= 10.0;
                continue;
            }
            // The decrease of the residual the linearised model predicts for the step,
            // `|r|^2 - |r - J dx|^2` (with a step tolerance only: see `SETTLED_RATIO`).
            let drop = match tolerance > 0.0 {
                true => 2.0 * step.dot(&jtr) - quadratic(&jtj, &step),
                false => f64::NAN,
            };
            // A step that the last one predicts to end the fit (see `SETTLED_RATIO`) is taken
            // without evaluating the model at its end: the residual there is the linearised
            // model's.
            if let (true, Some(before)) = (tolerance > 0.0, settled) {
                let length = step.norm();
                let q = length / before;
                let next_promise = q * q * step.dot(&jtr);
                if q <= SETTLED_RATIO
                    && s + step[3] >= 0.0
                    && drop > 0.0
                    && drop < sse
                    && q * length <= tolerance * (norm(nb) + ns)
                {
                    (b, s, sse) = (nb, ns, sse - drop);
                    promise = next_promise;
                    break;
                }
            }
            if last {
                // No step follows: the residual alone decides.
                let (next, n_used) = residual_at(k, groups, v, nb, ns);
                if n_used >= 4 && next < sse {
                    (b, s, sse, used) = (nb, ns, next, n_used);
                    capped = true;
                    break;
                }
                lambda *= 10.0;
                continue;
            }
            let next = equations_at(k, groups, v, nb, ns);
            if next.3 >= 4 && next.0 < sse {
                // Converged when the step no longer changes the fit noticeably.
                let small = step.norm() <= 1e-9 * (norm(b) + s) || sse - next.0 <= CONVERGED * sse;
                settled = ((sse - next.0 - drop).abs() <= SETTLED_MATCH * drop).then(|| step.norm());
                (b, s) = (nb, ns);
                (sse, jtj, jtr, used) = next;
                lambda = (lambda * 0.3).max(1e-9);
                accepted = !small;
                break;
            }
            lambda *= 10.0;
        }
        if !accepted {
            break;
        }
    }
    (used >= 4).then(|| {
        let rho = norm(b);
        GlossyFit {
            normal: scale(b, 1.0 / rho),
            diffuse: rho,
            specular: s,
            sse,
            used,
            converged: !capped,
            latitude: match tolerance > 0.0 && !capped {
                true => latitude(&jtj, b, s, promise, noise),
                false => 0.0,
            },
        }
    })
}

/// The observations of one facet in groups of `W` lanes (see [`Packed`]).
#[derive(Debug, Clone, Default)]
pub(super) struct Store {
    /// How many observations it holds.
    pub(super) len: usize,
    /// The groups of these observations (the first `len.div_ceil(W)`), then those of earlier
    /// facets, kept so that the next facets reset theirs instead of making them anew (see
    /// [`Group::reset`]).
    all: Vec<Group>,
    /// Scratch: the factors at the starting normal of a fit.
    factors: Vec<Factors>,
}

impl Group {
    /// What a group made anew holds where no observation was pushed since: no light, not a
    /// point light. (A lane's other terms are those of its observation once pushed, computed by
    /// [`Packed::prepare`] for every lane, or not read for a lane without one: the point
    /// lights' terms of a lane that is not a point light's are discarded.) A new group, made
    /// per facet, was written whole (1.7 kB of `f32` lanes at 16 lanes).
    #[inline]
    fn reset(&mut self) {
        self.value = [0.0; W];
        self.scale = [0.0; W];
        self.l = [[0.0; W]; 3];
        self.retro = [0.0; W];
        self.point = [false; W];
        self.mu = [0.0; W];
    }
}

impl Store {
    /// No observations.
    #[inline]
    pub(super) fn clear(&mut self) {
        self.len = 0;
    }

    /// The groups of the observations.
    #[cfg(test)]
    pub(super) fn groups(&self) -> &[Group] {
        &self.all[..self.len.div_ceil(W)]
    }

    /// The lane of the next observation.
    #[inline]
    fn next_lane(&mut self) -> (&mut Group, usize) {
        let (group, lane) = (self.len / W, self.len % W);
        if lane == 0 {
            match self.all.get_mut(group) {
                Some(g) => g.reset(),
                None => self.all.push(Group::default()),
            }
        }
        self.len += 1;
        (&mut self.all[group], lane)
    }

    /// [`Packed::push`].
    #[inline]
    pub(super) fn push(&mut self, value: f64, scale: f64, light: [f64; 3]) {
        let (g, i) = self.next_lane();
        g.value[i] = value as F;
        g.scale[i] = scale as F;
        for (j, &x) in light.iter().enumerate() {
            g.l[j][i] = x as F;
        }
    }

    /// [`Packed::push_point`].
    #[inline]
    pub(super) fn push_point(
        &mut self,
        value: f64,
        phi: f64,
        position: [f64; 3],
        axis: [f64; 3],
        mu: f64,
    ) {
        let (g, i) = self.next_lane();
        g.value[i] = value as F;
        g.phi[i] = phi;
        g.point[i] = true;
        g.mu[i] = mu;
        for j in 0..3 {
            g.position[j][i] = position[j];
            g.axis[j][i] = axis[j];
        }
    }

    /// [`Packed::push_observation`].
    #[inline]
    pub(super) fn push_observation(&mut self, o: &Observation) {
        let (g, i) = self.next_lane();
        g.value[i] = o.value as F;
        g.scale[i] = o.scale as F;
        for j in 0..3 {
            g.l[j][i] = o.light[j] as F;
            g.h[j][i] = o.half[j] as F;
        }
        g.fresnel[i] = o.fresnel as F;
        g.retro[i] = o.retro as F;
    }

    /// [`Packed::prepare`] with the view vector `v` and the lobe's `eta` and diffuse shape.
    pub(super) fn prepare(&mut self, v: [f64; 3], x: [f64; 3], eta: f64, retro: bool) {
        let n = self.len.div_ceil(W);
        prepare_dispatch(&mut self.all[..n], v, x, eta, retro);
    }
}

#[cfg(test)]
mod kernel_tests {
    use super::*;

    /// The starting albedos' sums in `f64` lanes ([`albedo_sums`]) and one observation after
    /// another ([`albedo_sums_in_order`]) agree to `f64` rounding, and with the scalar model's
    /// factors to the lanes' rounding, over lit and unlit lanes and a last group not full, under
    /// a lobe of each diffuse shape.
    #[test]
    fn the_albedo_sums_agree_in_both_orders() {
        let v = [0.0, 0.0, -1.0];
        let n = normalize([0.3, -0.2, -1.0]);
        let lanes_rounding = 1000.0 * f64::from(F::EPSILON);
        for lobe in [
            Lobe::new(0.3, 1.5),
            Lobe::retro(0.2, 1.5),
            Lobe::new(0.1, 1.0),
        ] {
            let k = Kernel::new(&lobe);
            let w = k.view(n, v).expect("the normal faces the camera");
            let mut store = Store::default();
            // 21 lights: the last group not full; the last ones behind the facet (unlit).
            let lights: Vec<[f64; 3]> = (0..21)
                .map(|i| {
                    let t = 0.7 * i as f64;
                    normalize([t.cos(), t.sin(), -1.5 + 0.1 * i as f64])
                })
                .collect();
            let mut scalar = [0.0; 5];
            for (i, &l) in lights.iter().enumerate() {
                let (value, phi) = (0.5 + 0.01 * i as f64, 1.0 + 0.1 * i as f64);
                store.push_observation(&Observation::new(value, phi, l, v, &lobe));
                if let Some(sh) = lobe.shade(n, l, v) {
                    let (d, s) = (phi * sh.diffuse, phi * sh.specular);
                    let terms = [d * d, d * s, s * s, d * value, s * value];
                    for (sum, term) in scalar.iter_mut().zip(terms) {
                        *sum += term;
                    }
                }
            }
            let mut factors = vec![Factors::default(); store.groups().len()];
            factors_of(&k, store.groups(), n, &w, v, &mut factors);
            let unlit = (0..lights.len()).filter(|&i| !factors[i / W].lit[i % W]).count();
            assert!(unlit > 0 && unlit < lights.len(), "{unlit} unlit");
            let lanes = albedo_sums(store.groups(), &factors);
            let in_order = albedo_sums_in_order(store.groups(), &factors);
            for (j, ((&lane, &ordered), &reference)) in
                lanes.iter().zip(&in_order).zip(&scalar).enumerate()
            {
                assert!(reference > 0.0, "{lobe:?} sum {j}: {scalar:?}");
                assert!(
                    (lane - ordered).abs() <= 1e-14 * ordered,
                    "{lobe:?} sum {j}: {lanes:?} against {in_order:?}"
                );
                assert!(
                    (ordered - reference).abs() <= lanes_rounding * reference,
                    "{lobe:?} sum {j}: {in_order:?} against the scalar model's {scalar:?}"
                );
            }
        }
    }
}
