//! Progress on stderr: a bar when stderr is a terminal, else one log line
//! at intervals (a batch job's or a log file's stderr), so long work is
//! never silent for minutes and logs are not flooded with redraws.

use std::io::{IsTerminal, Write};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use indicatif::{
    HumanDuration, ProgressBar, ProgressDrawTarget, ProgressState, ProgressStyle, TermLike,
};

/// How often a progress line is logged when stderr is not a terminal.
pub(crate) const LOG_INTERVAL: Duration = Duration::from_secs(10);

/// A progress bar of `len` steps labelled `message`: drawn as a bar when
/// stderr is a terminal; otherwise a line `message: pos/len (…)` is logged
/// every [`LOG_INTERVAL`] while the work goes on (nothing for work that
/// ends sooner).
pub fn bar(len: u64, message: &str) -> ProgressBar {
    if std::io::stderr().is_terminal() {
        let bar = ProgressBar::with_draw_target(Some(len), ProgressDrawTarget::stderr());
        bar.set_style(
            ProgressStyle::with_template("{msg:>12} [{bar:40}] {pos}/{len} ({rate}, eta {eta})")
                .unwrap_or_else(|_| ProgressStyle::default_bar())
                .with_key("eta", eta)
                .with_key("rate", rate)
                .progress_chars("=> "),
        );
        bar.set_message(message.to_string());
        bar
    } else {
        logged(len, message, LOG_INTERVAL, Box::new(std::io::stderr()))
    }
}

/// A progress bar that logs one line to `sink` at most every `interval`
/// (the first after `interval`), for stderr that is not a terminal.
pub(crate) fn logged(
    len: u64,
    message: &str,
    interval: Duration,
    sink: Box<dyn Write + Send>,
) -> ProgressBar {
    let lines = LogLines {
        interval,
        state: Mutex::new(LogState {
            sink,
            drawn: Vec::new(),
            pending: String::new(),
            last: Instant::now(),
        }),
    };
    // One redraw a second at most; `LogLines` keeps one in `interval`.
    let bar = ProgressBar::with_draw_target(
        Some(len),
        ProgressDrawTarget::term_like_with_hz(Box::new(lines), 1),
    );
    bar.set_style(
        ProgressStyle::with_template("{msg}: {pos}/{len} ({percent}%, {rate}, eta {eta})")
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .with_key("eta", eta)
            .with_key("rate", rate),
    );
    bar.set_message(message.to_string());
    bar
}

/// The estimated time left, or `unknown` before the first step is done
/// (indicatif's own estimate says `0s` then, which reads as "finished").
///
/// The estimate is the mean time per step so far times the steps left.
/// indicatif's own follows the recent rate, which suits many fast steps
/// but not a sweep whose tasks end minutes apart: between two of them the
/// recent rate decays to zero and its estimate grows to years.
fn eta(state: &ProgressState, out: &mut dyn std::fmt::Write) {
    let left = match time_left(state.pos(), state.len(), state.elapsed()) {
        Some(left) => format!("{:#}", HumanDuration(left)),
        None => "unknown".to_string(),
    };
    // A failed write only loses a cosmetic field.
    let _ = out.write_str(&left);
}

/// `elapsed × (len − pos) / pos`: the time left at the mean pace so far;
/// `None` before the first step (or without a length).
fn time_left(pos: u64, len: Option<u64>, elapsed: Duration) -> Option<Duration> {
    let len = len?;
    if pos == 0 {
        return None;
    }
    let left = len.saturating_sub(pos) as f64;
    Some(elapsed.mul_f64(left / pos as f64))
}

/// Steps per second over the whole work so far, or per minute or hour when
/// steps are slower (a sweep's tasks), so a slow but moving sweep does not
/// read `0/s`.
fn rate(state: &ProgressState, out: &mut dyn std::fmt::Write) {
    let _ = out.write_str(&pace(state.pos(), state.elapsed()));
}

fn pace(pos: u64, elapsed: Duration) -> String {
    let seconds = elapsed.as_secs_f64();
    if seconds <= 0.0 {
        return "-".to_string();
    }
    let per_second = pos as f64 / seconds;
    if per_second >= 1.0 || pos == 0 {
        format!("{per_second:.1}/s")
    } else if per_second * 60.0 >= 1.0 {
        format!("{:.1}/min", per_second * 60.0)
    } else {
        format!("{:.1}/h", per_second * 3600.0)
    }
}

/// A [`bar`] labelled `message` for work whose parts can take minutes
/// each (linking, the D estimators), of one part until the work sets its
/// own length: it ticks every second, so that a log gets a line every
/// [`LOG_INTERVAL`] while the work runs, not only when a part ends.
pub(crate) fn heartbeat(message: &str) -> ProgressBar {
    let bar = bar(1, message);
    bar.enable_steady_tick(Duration::from_secs(1));
    bar
}

/// A progress bar that never draws, for library callers and tests.
pub fn hidden() -> ProgressBar {
    ProgressBar::hidden()
}

/// A line for the person running scanloc, on standard error: a step waited
/// for, a shard imported, a damaged blob being rebuilt. Library code tells
/// its user things through this, its progress bars and `tracing`, never by
/// printing itself, so what reaches standard error is decided here. A
/// standard error that cannot be written is not an error of the work.
pub fn note(line: impl std::fmt::Display) {
    let _ = writeln!(std::io::stderr().lock(), "{line}");
}

/// [`note`] when standard error is a terminal only: a line for someone
/// watching, which a log file need not keep.
pub(crate) fn note_on_terminal(line: impl std::fmt::Display) {
    if std::io::stderr().is_terminal() {
        note(line);
    }
}

/// indicatif's terminal, turned into a log. A redraw writes the lines
/// printed above the bar (`ProgressBar::println`: an epoch's summary, a
/// finished task) and then the bar's own line, and ends with a flush: the
/// printed lines are logged at once, each once; the bar's line replaces the
/// pending one, logged if `interval` has passed since the last bar line.
struct LogLines {
    interval: Duration,
    state: Mutex<LogState>,
}

struct LogState {
    sink: Box<dyn Write + Send>,
    /// The non-blank lines of the redraw under way; the last is the bar's.
    drawn: Vec<String>,
    pending: String,
    last: Instant,
}

impl std::fmt::Debug for LogLines {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LogLines")
            .field("interval", &self.interval)
            .finish()
    }
}

impl LogLines {
    fn with_state(&self, act: impl FnOnce(&mut LogState)) -> std::io::Result<()> {
        // A poisoned lock only means a panic elsewhere; progress is cosmetic.
        let mut state = self.state.lock().unwrap_or_else(|p| p.into_inner());
        act(&mut state);
        Ok(())
    }
}

impl TermLike for LogLines {
    fn width(&self) -> u16 {
        160
    }

    fn move_cursor_up(&self, _n: usize) -> std::io::Result<()> {
        Ok(())
    }

    fn move_cursor_down(&self, _n: usize) -> std::io::Result<()> {
        Ok(())
    }

    fn move_cursor_right(&self, _n: usize) -> std::io::Result<()> {
        Ok(())
    }

    fn move_cursor_left(&self, _n: usize) -> std::io::Result<()> {
        Ok(())
    }

    fn write_line(&self, line: &str) -> std::io::Result<()> {
        self.write_str(line)
    }

    fn write_str(&self, text: &str) -> std::io::Result<()> {
        self.with_state(|state| {
            if !text.trim().is_empty() {
                state.drawn.push(text.trim().to_string());
            }
        })
    }

    fn clear_line(&self) -> std::io::Result<()> {
        Ok(())
    }

    fn flush(&self) -> std::io::Result<()> {
        let interval = self.interval;
        self.with_state(|state| {
            if let Some(bar) = state.drawn.pop() {
                // A closed stderr must not stop the work.
                for printed in std::mem::take(&mut state.drawn) {
                    let _ = writeln!(state.sink, "{printed}");
                }
                state.pending = bar;
            }
            if state.pending.is_empty() || state.last.elapsed() < interval {
                let _ = state.sink.flush();
                return;
            }
            // A closed stderr must not stop the work.
            let _ = writeln!(state.sink, "{}", state.pending);
            let _ = state.sink.flush();
            state.pending.clear();
            state.last = Instant::now();
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Arc;

    /// A sink the test can read back.
    #[derive(Clone, Default)]
    struct Shared(Arc<Mutex<Vec<u8>>>);

    impl Shared {
        /// Everything written so far, as text.
        fn text(&self) -> String {
            String::from_utf8(self.0.lock().unwrap().clone()).unwrap()
        }
    }

    impl Write for Shared {
        fn write(&mut self, bytes: &[u8]) -> std::io::Result<usize> {
            self.0.lock().unwrap().extend_from_slice(bytes);
            Ok(bytes.len())
        }
        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }

    /// Lines printed above the bar (an epoch's summary) reach the log at
    /// once and once each, however often the bar is redrawn.
    #[test]
    fn lines_printed_above_a_logged_bar_are_logged_at_once() {
        let sink = Shared::default();
        let bar = logged(
            10,
            "training",
            Duration::from_secs(3600),
            Box::new(sink.clone()),
        );
        bar.inc(1);
        bar.println("epoch 1: loss 2.5");
        bar.inc(1);
        bar.println("epoch 2: loss 2.1");
        for _ in 0..3 {
            bar.inc(1);
            bar.tick();
        }
        let text = sink.text();
        // The bar's own line waits for its interval (an hour here).
        assert_eq!(text, "epoch 1: loss 2.5\nepoch 2: loss 2.1\n");
    }

    #[test]
    fn logged_progress_writes_whole_lines_at_intervals_only() {
        let sink = Shared::default();
        let bar = logged(
            100,
            "locating",
            Duration::from_millis(300),
            Box::new(sink.clone()),
        );
        for _ in 0..5 {
            bar.inc(1);
        }
        // Within the first interval: nothing.
        assert!(sink.0.lock().unwrap().is_empty());
        std::thread::sleep(Duration::from_millis(1100));
        for _ in 0..5 {
            bar.inc(1);
        }
        std::thread::sleep(Duration::from_millis(1100));
        bar.inc(1);
        let text = sink.text();
        let lines: Vec<&str> = text.lines().collect();
        assert!(!lines.is_empty(), "no progress line in {text:?}");
        assert!(lines.len() <= 3, "too many lines: {text:?}");
        for line in &lines {
            assert!(line.starts_with("locating: "), "{line:?}");
            assert!(line.contains("/100"), "{line:?}");
            assert!(!line.contains('\r') && !line.contains('\x1b'), "{line:?}");
        }
    }

    #[test]
    fn the_time_left_is_unknown_until_a_step_is_done() {
        let sink = Shared::default();
        let bar = logged(5, "tasks done", Duration::ZERO, Box::new(sink.clone()));
        bar.tick();
        std::thread::sleep(Duration::from_millis(1100));
        bar.tick();
        let text = sink.text();
        let first = text.lines().next().expect("a progress line");
        assert!(
            first.contains("0/5") && first.ends_with("eta unknown)"),
            "{first:?}"
        );
    }

    #[test]
    fn the_time_left_follows_the_mean_pace_of_slow_steps() {
        // One task of five done after ten minutes: forty minutes left,
        // whatever the rate of the last seconds.
        let left = time_left(1, Some(5), Duration::from_secs(600)).unwrap();
        assert_eq!(left, Duration::from_secs(2400));
        assert_eq!(time_left(0, Some(5), Duration::from_secs(600)), None);
        assert_eq!(
            time_left(5, Some(5), Duration::from_secs(600)),
            Some(Duration::ZERO)
        );
        assert_eq!(pace(1, Duration::from_secs(600)), "6.0/h");
        assert_eq!(pace(3, Duration::from_secs(60)), "3.0/min");
        assert_eq!(pace(250, Duration::from_secs(10)), "25.0/s");
    }

    #[test]
    fn a_slow_sweep_logs_a_finite_time_left() {
        let sink = Shared::default();
        let bar = logged(5, "tasks done", Duration::ZERO, Box::new(sink.clone()));
        bar.tick();
        std::thread::sleep(Duration::from_millis(1100));
        bar.inc(1);
        std::thread::sleep(Duration::from_millis(1100));
        bar.tick();
        let text = sink.text();
        let last = text.lines().last().expect("a progress line");
        // About 2.2 s for one step: about 9 s left, never years.
        assert!(last.contains("1/5") && last.contains("/min"), "{last:?}");
        let eta = last.rsplit("eta ").next().unwrap().trim_end_matches(')');
        let seconds: u64 = eta.trim_end_matches('s').parse().unwrap_or(u64::MAX);
        assert!((5..=20).contains(&seconds), "{last:?}");
    }
}
