//! Encoded image bytes → XFeat: a named error (undecodable, too small, over the memory
//! limit) or keypoints, never a panic.
#![no_main]
use std::sync::OnceLock;

use libfuzzer_sys::fuzz_target;
use paraformer::{GrayImage, XFeat};

static XFEAT: OnceLock<XFeat> = OnceLock::new();

fuzz_target!(|data: &[u8]| {
    let xf = XFEAT.get_or_init(|| {
        paraformer::memory::set_memory_limit(Some(1 << 30));
        XFeat::pretrained().expect("embedded weights load")
    });
    if let Ok(img) = GrayImage::from_encoded(data) {
        let _ = xf.detect_and_compute(&img, Some(256));
    }
});
