//! Random draws shared by the trainer and the augmentation code.

use rand::Rng;

/// Two independent standard normal draws from the caller's generator
/// (Box-Muller: `u1` in (0, 1], `u2` in [0, 1), `r = sqrt(-2 ln u1)`,
/// `(r cos 2 pi u2, r sin 2 pi u2)`). Kept rather than `rand_distr`'s
/// ziggurat so that runs with a given seed, and the figures measured with
/// them (docs/), reproduce: the trainer's action noise and the STF's
/// Gaussian neighbourhood noise have always used this transform.
pub fn normal_pair<R: Rng + ?Sized>(rng: &mut R) -> (f64, f64) {
    let u1: f64 = 1.0 - rng.random::<f64>();
    let u2: f64 = rng.random::<f64>();
    let r = (-2.0 * u1.ln()).sqrt();
    let th = std::f64::consts::TAU * u2;
    (r * th.cos(), r * th.sin())
}

/// Fill `z` with independent standard normal draws, taken in pairs from
/// [`normal_pair`] in order (the second draw of the last pair is dropped
/// when `z.len()` is odd): the trainer's action noise, `N * act_dim`
/// values per policy step.
pub fn fill_normal<R: Rng + ?Sized>(z: &mut [f64], rng: &mut R) {
    for pair in z.chunks_mut(2) {
        let (a, b) = normal_pair(rng);
        pair[0] = a;
        if pair.len() > 1 {
            pair[1] = b;
        }
    }
}
