//! Status codes, this thread's last error, and [`guard`], which every exported function
//! runs its body in: a panic becomes an error code, never an unwind into C.

use std::cell::RefCell;
use std::ffi::{c_char, c_int, CStr, CString};

/// Success.
pub const VOXMAP_OK: c_int = 0;
/// A required pointer argument was null.
pub const VOXMAP_ERR_NULL: c_int = -1;
/// An argument is out of its domain (not finite, outside the index space, an inverted box,
/// not UTF-8, a second loan, ...).
pub const VOXMAP_ERR_INVALID: c_int = -2;
/// A file could not be read or is not a valid map or snapshot.
pub const VOXMAP_ERR_FILE: c_int = -3;
/// Shared memory or the service failed (connect, loan, send, receive).
pub const VOXMAP_ERR_IPC: c_int = -4;
/// The service did not answer in time (is it running?).
pub const VOXMAP_ERR_TIMEOUT: c_int = -5;
/// The service answered with an error (a save to a bad path, a corrupt map to load).
pub const VOXMAP_ERR_REJECTED: c_int = -6;
/// A bug inside voxmap (a Rust panic, caught at the boundary).
pub const VOXMAP_ERR_INTERNAL: c_int = -7;

thread_local! {
    static LAST: RefCell<CString> = RefCell::new(CString::default());
}

/// An error to hand to C: its code and its message.
pub(crate) struct Failure {
    pub code: c_int,
    pub message: String,
}

impl Failure {
    pub fn new(code: c_int, message: impl Into<String>) -> Self {
        Self {
            code,
            message: message.into(),
        }
    }

    /// A required pointer `what` was null.
    pub fn null(what: &str) -> Self {
        Self::new(VOXMAP_ERR_NULL, format!("{what} is null"))
    }

    pub fn invalid(message: impl Into<String>) -> Self {
        Self::new(VOXMAP_ERR_INVALID, message)
    }

    /// An error with its chain of causes, `a: b: c`.
    pub fn chain(code: c_int, e: &dyn std::error::Error) -> Self {
        Self::new(code, voxmap_client::error_chain(e))
    }

    pub fn client(e: &voxmap_client::ClientError) -> Self {
        use voxmap_client::ClientError as E;
        let code = match e {
            E::Timeout(_) => VOXMAP_ERR_TIMEOUT,
            E::Rejected(_) => VOXMAP_ERR_REJECTED,
            E::BadRequest(_) => VOXMAP_ERR_INVALID,
            E::Snapshot(_) => VOXMAP_ERR_FILE,
            _ => VOXMAP_ERR_IPC,
        };
        Self::chain(code, e)
    }
}

fn set_last(message: &str) {
    // A message with an interior NUL is cut there.
    let bytes: Vec<u8> = message.bytes().take_while(|&b| b != 0).collect();
    let c = CString::new(bytes).unwrap_or_default();
    LAST.with(|l| *l.borrow_mut() = c);
}

/// Run `body`; on failure or panic, record the message as this thread's last error and
/// return `on_error(code)`.
pub(crate) fn guard<T>(
    on_error: impl FnOnce(c_int) -> T,
    body: impl FnOnce() -> Result<T, Failure>,
) -> T {
    match std::panic::catch_unwind(std::panic::AssertUnwindSafe(body)) {
        Ok(Ok(v)) => v,
        Ok(Err(f)) => {
            set_last(&f.message);
            on_error(f.code)
        }
        Err(p) => {
            let why = p
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| p.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "unknown".into());
            set_last(&format!("internal error in voxmap (please report): {why}"));
            on_error(VOXMAP_ERR_INTERNAL)
        }
    }
}

/// A status-code function's guard: 0 or more on success, the error code on failure.
pub(crate) fn status(body: impl FnOnce() -> Result<c_int, Failure>) -> c_int {
    guard(|code| code, body)
}

/// A C string argument as UTF-8.
///
/// # Safety
/// `s` is null or points to a NUL-terminated string.
pub(crate) unsafe fn str_arg<'a>(s: *const c_char, what: &str) -> Result<&'a str, Failure> {
    if s.is_null() {
        return Err(Failure::null(what));
    }
    // SAFETY: non-null, and the caller promises a NUL-terminated string.
    unsafe { CStr::from_ptr(s) }
        .to_str()
        .map_err(|_| Failure::invalid(format!("{what} is not UTF-8")))
}

/// A reference from a pointer argument.
///
/// # Safety
/// `p` is null or points to a live `T` (one returned by this library and not yet freed).
pub(crate) unsafe fn ref_arg<'a, T>(p: *const T, what: &str) -> Result<&'a T, Failure> {
    // SAFETY: the caller's promise.
    unsafe { p.as_ref() }.ok_or_else(|| Failure::null(what))
}

/// A mutable reference from a pointer argument.
///
/// # Safety
/// `p` is null or points to a live `T` no other call uses at the same time.
pub(crate) unsafe fn mut_arg<'a, T>(p: *mut T, what: &str) -> Result<&'a mut T, Failure> {
    // SAFETY: the caller's promise.
    unsafe { p.as_mut() }.ok_or_else(|| Failure::null(what))
}

/// Three doubles from an array argument.
///
/// # Safety
/// `p` is null or points to at least 3 doubles.
pub(crate) unsafe fn xyz_arg(p: *const f64, what: &str) -> Result<[f64; 3], Failure> {
    if p.is_null() {
        return Err(Failure::null(what));
    }
    // SAFETY: non-null, and the caller promises 3 readable doubles.
    Ok(unsafe { [*p, *p.add(1), *p.add(2)] })
}

/// A new handle for C, freed by [`free_handle`].
pub(crate) fn into_handle<T>(v: T) -> *mut T {
    Box::into_raw(Box::new(v))
}

/// Free a handle made by [`into_handle`] (null is ignored), inside the guard.
///
/// # Safety
/// `p` is null or a handle from [`into_handle`] of this type, not yet freed.
pub(crate) unsafe fn free_handle<T>(p: *mut T) {
    guard(
        |_| (),
        || {
            if !p.is_null() {
                // SAFETY: the caller's promise: made by `Box::into_raw`, freed once.
                drop(unsafe { Box::from_raw(p) });
            }
            Ok(())
        },
    )
}

/// A handle connected to map `map` under `prefix` by `connect`; null on failure.
///
/// # Safety
/// `prefix` and `map` are null or NUL-terminated strings.
pub(crate) unsafe fn connect_handle<T>(
    prefix: *const c_char,
    map: *const c_char,
    connect: impl FnOnce(&str, &str) -> Result<T, voxmap_client::ClientError>,
) -> *mut T {
    guard(
        |_| std::ptr::null_mut(),
        || {
            // SAFETY: the caller's promises.
            let (prefix, map) = unsafe { (str_arg(prefix, "prefix")?, str_arg(map, "map")?) };
            let handle = connect(prefix, map).map_err(|e| Failure::client(&e))?;
            Ok(into_handle(handle))
        },
    )
}

/// This thread's last failure, as a NUL-terminated UTF-8 message; `""` when no call on
/// this thread has failed. Never null. The pointer stays valid until this thread's next
/// failing call into voxmap.
#[no_mangle]
pub extern "C" fn voxmap_last_error() -> *const c_char {
    LAST.with(|l| l.borrow().as_ptr())
}
