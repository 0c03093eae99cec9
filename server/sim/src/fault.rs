//! MuJoCo errors as values.
//!
//! MuJoCo reports a fatal error (`mju_error`) through its log handler and expects the handler never to
//! return; both MuJoCo's default handler and mujoco-rs' hook then end the process. One episode's fault must
//! not take the server down, so this module installs a process-wide handler that *unwinds* out of the C
//! code (libmujoco has `.eh_frame` unwind tables on x86_64, and C frames hold no destructors) with a
//! private payload. [`guarded`] catches exactly that payload and turns it into a message; the caller must
//! treat the `mjData` it was working on as poisoned, because MuJoCo's arena stack marks were skipped.
//! Warnings and info messages go to the `log` crate instead of stderr.
//!
//! Do not also call `mujoco_rs::logging::install_logging_hook`/`set_log_handler`: they replace this
//! handler with one that exits the process on errors.
use std::ffi::CStr;
use std::panic::{self, AssertUnwindSafe};
use std::sync::Once;

use mujoco_rs::mujoco_c::{mjLogMessage, mju_setLogHandler};

/// The panic payload of a MuJoCo error: private, so no other panic is mistaken for one.
struct MujocoErrorPayload(String);

static INSTALL: Once = Once::new();

/// Layout mirror of MuJoCo 3.17's `mjLogMessage` (mujoco-rs keeps the fields crate-private and its
/// accessors panic on invalid UTF-8, which must not happen inside the handler).
#[repr(C)]
#[allow(dead_code)] // fields kept for layout
struct RawLogMessage {
    level: std::os::raw::c_int,
    topic: std::os::raw::c_int,
    subject: [std::os::raw::c_char; 1024],
    body: *const std::os::raw::c_char,
    func: *const std::os::raw::c_char,
    file: *const std::os::raw::c_char,
    line: std::os::raw::c_int,
    timestamp: u8,
}
const _: () = assert!(std::mem::size_of::<RawLogMessage>() == std::mem::size_of::<mjLogMessage>());

/// Reads a NUL-terminated C string, tolerating null and invalid UTF-8.
fn c_text(ptr: *const std::os::raw::c_char) -> String {
    if ptr.is_null() {
        return String::new();
    }
    // SAFETY: MuJoCo hands NUL-terminated strings that live for the duration of the handler call.
    unsafe { CStr::from_ptr(ptr) }.to_string_lossy().into_owned()
}

/// Formats a MuJoCo log message as `func: subject — body` and returns it with its level.
///
/// # Safety
/// `msg` must point to a valid `mjLogMessage` for the duration of the call.
unsafe fn message_text(msg: *const mjLogMessage) -> (i32, String) {
    // SAFETY: the caller guarantees `msg` is valid; RawLogMessage has the same layout.
    let m = unsafe { &*(msg as *const RawLogMessage) };
    let subject_bytes: Vec<u8> =
        m.subject.iter().take_while(|&&c| c != 0).map(|&c| c as u8).collect();
    let subject = String::from_utf8_lossy(&subject_bytes);
    let func = c_text(m.func);
    let body = c_text(m.body);
    let mut text = String::new();
    if !func.is_empty() {
        text.push_str(&func);
        text.push_str(": ");
    }
    text.push_str(subject.trim_end());
    if !body.is_empty() {
        text.push_str(" — ");
        text.push_str(&body);
    }
    (m.level, text)
}

/// The process-wide MuJoCo log handler: errors unwind, everything else is logged.
///
/// `resume_unwind` (not `panic!`) starts the unwind, so the panic hook does not print a backtrace for
/// what is an expected, handled condition.
extern "C-unwind" fn log_handler(msg: *const mjLogMessage) {
    // SAFETY: MuJoCo never passes null and the message outlives this call.
    let (level, text) = unsafe { message_text(msg) };
    match level {
        3 => panic::resume_unwind(Box::new(MujocoErrorPayload(text))),
        2 => log::warn!(target: "mujoco", "{text}"),
        1 => log::info!(target: "mujoco", "{text}"),
        _ => log::debug!(target: "mujoco", "{text}"),
    }
}

/// Installs [`log_handler`] once per process. Called by every guarded entry point, so users never
/// need to call it; it is public for programs that want MuJoCo's model-loading warnings routed too.
pub fn install_fault_handler() {
    INSTALL.call_once(|| {
        type CUnwindHandler = extern "C-unwind" fn(*const mjLogMessage);
        type CHandler = unsafe extern "C" fn(*const mjLogMessage);
        let handler: CUnwindHandler = log_handler;
        // SAFETY: the two function-pointer types differ only in the unwind ABI annotation; the calling
        // convention is identical. MuJoCo stores the pointer in a global, which `Once` writes exactly once.
        unsafe {
            let c_handler: CHandler = std::mem::transmute::<CUnwindHandler, CHandler>(handler);
            mju_setLogHandler(Some(c_handler));
        }
    });
}

/// Runs `f`, converting a MuJoCo error raised inside it into `Err(message)`.
///
/// Any other panic is propagated unchanged. After an `Err`, the `mjData` touched by `f` is in an
/// undefined (but memory-safe to drop) state and must not be stepped again.
pub fn guarded<R>(f: impl FnOnce() -> R) -> Result<R, String> {
    install_fault_handler();
    match panic::catch_unwind(AssertUnwindSafe(f)) {
        Ok(r) => Ok(r),
        Err(payload) => match payload.downcast::<MujocoErrorPayload>() {
            Ok(err) => Err(err.0),
            Err(other) => panic::resume_unwind(other),
        },
    }
}

/// The MuJoCo entry points a simulation calls, re-declared with the `C-unwind` ABI: mujoco-rs declares
/// them `extern "C"`, which tells the compiler they never unwind, and unwinding a MuJoCo error through
/// such a call would be undefined behaviour. Same symbols, same signatures.
pub mod ffi {
    use mujoco_rs::mujoco_c::{mjData, mjModel, mjtNum};
    unsafe extern "C-unwind" {
        pub fn mj_step1(m: *const mjModel, d: *mut mjData);
        pub fn mj_step2(m: *const mjModel, d: *mut mjData);
        pub fn mj_forward(m: *const mjModel, d: *mut mjData);
        pub fn mj_resetData(m: *const mjModel, d: *mut mjData);
        pub fn mj_kinematics(m: *const mjModel, d: *mut mjData);
        pub fn mj_comPos(m: *const mjModel, d: *mut mjData);
        pub fn mj_camlight(m: *const mjModel, d: *mut mjData);
        pub fn mj_getState(m: *const mjModel, d: *const mjData, state: *mut mjtNum, sig: std::os::raw::c_int);
    }
}
