// Smoke check of haptree_lcmtypes.jar (CTest java_lcmtypes_jar): finds every haptree.lcmt_* class in
// the jar, checks it is an LCMEncodable that survives encode -> decode with its fingerprint, and that
// lcm-spy's main class loads beside them. Exit 0 only if the expected number of types was found.
import java.io.DataInputStream;
import java.io.ByteArrayInputStream;
import java.util.ArrayList;
import java.util.Enumeration;
import java.util.List;
import java.util.jar.JarEntry;
import java.util.jar.JarFile;

public class HaptreeTypesCheck {
  public static void main(String[] args) throws Exception {
    int expected = Integer.parseInt(args[0]);
    List<String> names = new ArrayList<>();
    for (String part : System.getProperty("java.class.path").split(":")) {
      if (!part.endsWith("haptree_lcmtypes.jar")) continue;
      try (JarFile jf = new JarFile(part)) {
        for (Enumeration<JarEntry> e = jf.entries(); e.hasMoreElements();) {
          String n = e.nextElement().getName();
          if (n.startsWith("haptree/lcmt_") && n.endsWith(".class") && !n.contains("$"))
            names.add(n.substring(0, n.length() - 6).replace('/', '.'));
        }
      }
    }
    for (String n : names) {
      Class<?> c = Class.forName(n);
      if (!lcm.lcm.LCMEncodable.class.isAssignableFrom(c)) throw new AssertionError(n + " is not LCMEncodable");
      lcm.lcm.LCMEncodable m = (lcm.lcm.LCMEncodable) c.getConstructor().newInstance();
      for (java.lang.reflect.Field f : c.getFields())   // Java leaves strings null; LCM cannot encode null
        if (f.getType() == String.class) f.set(m, "check");
      java.io.ByteArrayOutputStream bos = new java.io.ByteArrayOutputStream();
      m.encode(new java.io.DataOutputStream(bos));
      byte[] bytes = bos.toByteArray();
      long fp = c.getField("LCM_FINGERPRINT").getLong(null);
      long head = new DataInputStream(new ByteArrayInputStream(bytes)).readLong();
      if (head != fp) throw new AssertionError(n + ": encoded fingerprint " + Long.toHexString(head));
      Object back = c.getConstructor(byte[].class).newInstance((Object) bytes);
      System.out.printf("ok %s fingerprint %016x, %d bytes%n", n, fp, bytes.length);
    }
    Class.forName("lcm.spy.Spy");
    System.out.println("ok lcm.spy.Spy loads");
    if (names.size() != expected) {
      System.out.println("FAIL: " + names.size() + " haptree types in the jar, expected " + expected);
      System.exit(1);
    }
  }
}
