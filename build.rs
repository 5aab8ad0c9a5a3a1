//! Links libmujoco with an rpath so binaries and tests run without LD_LIBRARY_PATH.
use std::path::Path;

fn main() {
    println!("cargo::rerun-if-env-changed=MUJOCO_DYNAMIC_LINK_DIR");
    let Ok(dir) = std::env::var("MUJOCO_DYNAMIC_LINK_DIR") else {
        println!(
            "cargo::error=MUJOCO_DYNAMIC_LINK_DIR is not set; .cargo/config.toml sets it. Run `make setup`."
        );
        return;
    };
    if !Path::new(&dir).join("libmujoco.so").exists() {
        println!(
            "cargo::error=libmujoco.so not found in {dir}. Run `make setup` (scripts/setup.sh) first."
        );
        return;
    }
    println!("cargo::rerun-if-changed={dir}/libmujoco.so");
    println!("cargo::rustc-link-arg=-Wl,-rpath,{dir}");
}
