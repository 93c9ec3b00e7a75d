// Screenshot of the X display (for docs/img/lcm-spy.png; not part of the build):
//   java java/Screenshot.java OUT.png DELAY_MS [X Y]...   double-clicks each (X, Y) first, 1.5 s apart.
import java.awt.Rectangle;
import java.awt.Robot;
import java.awt.Toolkit;
import java.awt.event.InputEvent;
import java.io.File;
import javax.imageio.ImageIO;

public class Screenshot {
  public static void main(String[] a) throws Exception {
    Robot r = new Robot();
    Thread.sleep(Long.parseLong(a[1]));
    for (int i = 2; i + 1 < a.length; i += 2) {
      r.mouseMove(Integer.parseInt(a[i]), Integer.parseInt(a[i + 1]));
      Thread.sleep(300);
      for (int k = 0; k < 2; ++k) {
        r.mousePress(InputEvent.BUTTON1_DOWN_MASK);
        Thread.sleep(40);
        r.mouseRelease(InputEvent.BUTTON1_DOWN_MASK);
        Thread.sleep(60);
      }
      Thread.sleep(1500);
    }
    ImageIO.write(r.createScreenCapture(new Rectangle(Toolkit.getDefaultToolkit().getScreenSize())), "png", new File(a[0]));
  }
}
