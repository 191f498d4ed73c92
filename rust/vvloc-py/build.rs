//! Records the cargo profile so Python can refuse to benchmark a debug build.
fn main() {
    let profile = std::env::var("PROFILE").unwrap_or_else(|_| "unknown".to_string());
    println!("cargo:rustc-env=VVLOC_BUILD_PROFILE={profile}");
    println!("cargo:rerun-if-env-changed=PROFILE");
}
