//! Rendered targets against their known geometry.

use super::*;

fn board() -> Chessboard {
    Chessboard {
        board: Board::parse("9x6", 15.0).unwrap(),
        border_squares: 1.0,
    }
}

#[test]
fn a_board_on_the_table_projects_its_corners_where_the_rig_camera_puts_them() {
    let mut rig = Rig::default_rig();
    rig.camera.rotation_deg = [0.5, -0.4, 1.0];
    let b = board();
    let pose = BoardPose::on_table(&b, &rig);
    let world_from_board = board_to_world();
    let [cx, cy] = b.centre();
    for p in b.object_points() {
        let bp = Vector3::from(p);
        let in_camera = pose.rotation * bp + pose.translation;
        let world = world_from_board * (bp - Vector3::new(cx, cy, 0.0));
        let (u, v) = rig.camera.project(&world).unwrap();
        let (ex, ey) = (
            rig.camera.fx * in_camera.x / in_camera.z + rig.camera.cx,
            rig.camera.fy * in_camera.y / in_camera.z + rig.camera.cy,
        );
        assert!(
            (u - ex).abs() < 1e-6 && (v - ey).abs() < 1e-6,
            "{u},{v} vs {ex},{ey}"
        );
    }
    // The first corner is at the top left of the image, the rows run to the right.
    let first = rig
        .camera
        .project(&(world_from_board * Vector3::new(-cx, -cy, 0.0)))
        .unwrap();
    assert!(first.0 < rig.camera.cx && first.1 < rig.camera.cy);
}

#[test]
fn the_rendered_board_is_dark_and_light_where_the_squares_are() {
    let rig = Rig::default_rig();
    let window = SensorWindow::centred(4928, 3264, 616, 408, 8.0);
    let b = board();
    let pose = BoardPose::on_table(&b, &rig);
    let render = ViewRender {
        noise_levels: 0.0,
        ..ViewRender::default()
    };
    let grid = RayGrid::new(&rig.camera, window, 616, 408, render.supersample);
    let image = render_chessboard(&grid, &b, &pose, &render);
    // The centre of the first black square (board (-s/2, -s/2)) and a white one next to it.
    let s = b.board.square_m;
    let [cx, cy] = b.centre();
    let at = |bx: f64, by: f64| {
        let w = board_to_world() * Vector3::new(bx - cx, by - cy, 0.0);
        let (u, v) = rig.camera.project(&w).unwrap();
        let x = ((u - window.x0) / window.step).round() as usize;
        let y = ((v - window.y0) / window.step).round() as usize;
        image.data[y * 616 + x]
    };
    assert!(at(-0.5 * s, -0.5 * s) < 40, "{}", at(-0.5 * s, -0.5 * s));
    assert!(at(0.5 * s, -0.5 * s) > 180);
    // Off the paper the camera sees the background.
    assert_eq!(image.data[0], 90);
}
