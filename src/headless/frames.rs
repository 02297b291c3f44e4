//! What each headless frame did, and running frames until the illumination is finished.

use super::*;

fn count_of(counts: &[(CloudPass, u32)], pass: CloudPass) -> u32 {
    counts
        .iter()
        .find(|(p, _)| *p == pass)
        .map_or(0, |(_, n)| *n)
}

/// What one frame did.
#[derive(Clone, Debug, Default)]
pub struct FrameStats {
    /// Wall-clock time of the frame's `app.update()` and GPU poll, milliseconds.
    pub wall_ms: f64,
    /// Runs of each pass this frame.
    pub passes: Vec<(CloudPass, u32)>,
    /// Compute dispatches of each pass this frame.
    pub dispatches: Vec<(CloudPass, u32)>,
    /// GPU time of each pass that ran, when the adapter reported it.
    pub gpu_ms: HashMap<CloudPass, f64>,
}

impl FrameStats {
    /// Runs of `pass` this frame.
    pub fn runs(&self, pass: CloudPass) -> u32 {
        count_of(&self.passes, pass)
    }

    /// Compute dispatches of `pass` this frame.
    pub fn dispatches(&self, pass: CloudPass) -> u32 {
        count_of(&self.dispatches, pass)
    }

    /// Runs of the illumination and sort passes (everything but the draw).
    pub fn work(&self) -> u32 {
        self.passes
            .iter()
            .filter(|(p, _)| *p != CloudPass::Draw)
            .map(|(_, n)| n)
            .sum()
    }
}

/// Renders frames and attributes GPU times (which arrive a few frames late) to the frames whose
/// passes produced them.
#[derive(Default)]
pub struct FrameRecorder {
    /// Every recorded frame, in order.
    pub frames: Vec<FrameStats>,
    counted: [u32; PASSES],
    dispatched: [u32; PASSES],
    last_seen: HashMap<DiagnosticPath, Instant>,
    waiting: HashMap<CloudPass, VecDeque<usize>>,
}

impl FrameRecorder {
    /// Renders one frame and records it.
    pub fn frame(&mut self, app: &mut App) -> Result<&FrameStats, HeadlessError> {
        let start = Instant::now();
        update(app)?;
        let wall_ms = start.elapsed().as_secs_f64() * 1e3;
        let counters = app.world().resource::<CloudPassCounters>();
        let passes = counters.since(&mut self.counted).to_vec();
        let dispatches = counters.dispatches_since(&mut self.dispatched).to_vec();
        let index = self.frames.len();
        for &(pass, runs) in &passes {
            if runs > 0 {
                self.waiting.entry(pass).or_default().push_back(index);
            }
        }
        self.frames.push(FrameStats {
            wall_ms,
            passes,
            dispatches,
            gpu_ms: HashMap::new(),
        });
        self.collect_gpu_times(app);
        Ok(&self.frames[index])
    }

    /// Runs of `pass` over every recorded frame.
    pub fn total(&self, pass: CloudPass) -> u32 {
        self.frames.iter().map(|f| f.runs(pass)).sum()
    }

    /// Updates without recording (to let late GPU times and screenshots arrive).
    pub fn drain(&mut self, app: &mut App) -> Result<(), HeadlessError> {
        update(app)?;
        let counters = app.world().resource::<CloudPassCounters>();
        counters.since(&mut self.counted);
        counters.dispatches_since(&mut self.dispatched);
        self.collect_gpu_times(app);
        Ok(())
    }

    fn collect_gpu_times(&mut self, app: &App) {
        let Some(store) = app.world().get_resource::<DiagnosticsStore>() else {
            return;
        };
        for pass in CloudPass::ALL {
            for path in pass.diagnostic_paths() {
                self.collect_gpu_time(store, pass, &path);
            }
        }
    }
}

impl FrameRecorder {
    /// The GPU time of `pass` under `path`, if a new measurement arrived: the frame waiting longest
    /// for that pass's time gets it (added to what it holds from the pass's other paths).
    fn collect_gpu_time(
        &mut self,
        store: &DiagnosticsStore,
        pass: CloudPass,
        path: &DiagnosticPath,
    ) {
        let Some(diagnostic) = store.get(path) else {
            return;
        };
        let Some(latest) = diagnostic.measurement().map(|m| m.time) else {
            return;
        };
        if self.last_seen.get(path) == Some(&latest) {
            return;
        }
        self.last_seen.insert(path.clone(), latest);
        // One frame's spans of a pass (e.g. one per cloud and view) share the sync instant.
        let total: f64 = diagnostic
            .measurements()
            .filter(|m| m.time == latest)
            .map(|m| m.value)
            .sum();
        if let Some(frame) = self.waiting.get_mut(&pass).and_then(VecDeque::pop_front) {
            *self.frames[frame].gpu_ms.entry(pass).or_default() += total;
        }
    }
}

/// Why headless rendering could not go on.
#[derive(Debug, thiserror::Error)]
pub enum HeadlessError {
    /// Waiting for the GPU failed (a lost device, for example).
    #[error("waiting for the GPU failed: {0}")]
    Poll(String),
    /// The app asked to exit (Bevy's render error handler does after a GPU error).
    #[error("the renderer asked to exit: {0:?}")]
    Exited(AppExit),
    /// The illumination was still being computed after the given number of frames.
    #[error("the scene did not reach a finished image within {max_frames} frames")]
    NotSteady {
        /// The frames rendered.
        max_frames: usize,
    },
    /// The screenshot did not come back from the GPU.
    #[error("the screenshot did not arrive within {frames} frames")]
    NoScreenshot {
        /// The frames waited.
        frames: usize,
    },
    /// A captured image is not in the format [`decode_rgba16f`] reads.
    #[error("expected an Rgba16Float image with data, got {format:?}")]
    Format {
        /// The image's format.
        format: TextureFormat,
    },
}

/// One `app.update()` plus a blocking GPU poll, so readbacks and timings arrive deterministically.
pub fn update(app: &mut App) -> Result<(), HeadlessError> {
    app.update();
    if let Some(device) = app
        .sub_app(RenderApp)
        .world()
        .get_resource::<RenderDevice>()
    {
        device
            .poll(PollType::wait_indefinitely())
            .map_err(|e| HeadlessError::Poll(e.to_string()))?;
    }
    match app.should_exit() {
        Some(exit) => Err(HeadlessError::Exited(exit)),
        None => Ok(()),
    }
}

/// Renders until the clouds are drawn with finished illumination: a frame that does no
/// illumination or sort work and draws all `drawable_clouds` (for a scene,
/// [`SceneTarget::drawable_clouds`]), or, when some cloud is out of view, the second frame in a
/// row without work. Returns the frames it took.
pub fn render_until_steady(
    app: &mut App,
    recorder: &mut FrameRecorder,
    drawable_clouds: u32,
    max_frames: usize,
) -> Result<usize, HeadlessError> {
    let mut idle_before = false;
    for n in 1..=max_frames {
        let stats = recorder.frame(app)?;
        let idle = stats.work() == 0;
        if n > 1 && idle && (stats.runs(CloudPass::Draw) >= drawable_clouds || idle_before) {
            return Ok(n);
        }
        idle_before = idle && n > 1;
    }
    Err(HeadlessError::NotSteady { max_frames })
}
