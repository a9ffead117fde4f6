/**
 * The experiment's wording that a lab is most likely to adapt: the instructions. The consent text is
 * the server's (`consent_file` in conf/serve.yaml), so that its version is stored with each consent.
 */

export function instructionPages(session) {
  const bonus = `${session.currency}${session.bonus_per_unit.toFixed(2)}`;
  return [
    `<div class="text-page">
      <h2>Welcome</h2>
      <p>In this study you stack blocks to build towers that reach out as far as possible to the
      side, like a balcony, without falling down.</p>
      <p>Each tower is built from a sequence of blocks that you see from the start. The first
      block already stands on the ground, in the middle. You place the others one by one, in the
      order given.</p>
    </div>`,
    `<div class="text-page">
      <h2>Reaching out</h2>
      <p>The further your tower reaches to the left or right of the middle, the more you earn:
      ${bonus} per unit of reach, as long as the tower stands.</p>
      <p>But if a block falls, the tower's trial is over and earns nothing. You decide how much
      risk to take.</p>
      <p>A short tutorial follows to show you how it works.</p>
    </div>`,
  ];
}
