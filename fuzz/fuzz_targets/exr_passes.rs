//! The EXR pass / C_T readers on arbitrary bytes: must return `Ok` or `Err`, never panic,
//! hang or allocate beyond the header-size guard.
#![no_main]
use libfuzzer_sys::fuzz_target;
use std::path::Path;

fuzz_target!(|data: &[u8]| {
    let path = Path::new("fuzz.exr");
    if let Ok(chans) = pixl_core::exrio::read_exr_channels_from_bytes(data, path) {
        if let Ok(set) = pixl_intrinsics::compose::PassSet::from_exr_channels(&chans, None) {
            let _ = pixl_intrinsics::compose::compose(&set, &Default::default());
        }
        // The C_T reader goes through a file; use a per-process file on tmpfs.
        let tmp = std::env::temp_dir().join(format!("pixl-fuzz-ct-{}.exr", std::process::id()));
        if std::fs::write(&tmp, data).is_ok() {
            let _ = pixl_intrinsics::ct::read_ct(&tmp);
        }
    }
});
